"""ZOA stability lobes (Altintas & Budak 1995): closed-form SDOF limit, directional factors
against the milling force model, and 2-D lobes with cross terms against a direct solution
of the characteristic equation."""

import numpy as np
import pytest
from scipy.optimize import fsolve

from feedbench.analysis.stability import directional_matrix, zoa_lobes
from feedbench.models.milling import CuttingCoefficients, chip_thickness, engagement_angles, tooth_force
from feedbench.models.structure import ModalStructure

# Insperger–Stépán single-DOF benchmark
N_IS = 2
K_T_IS, K_N_IS = 6e8, 2e8
F_N_IS, ZETA_IS, M_IS = 922.0, 0.011, 0.03993


def sdof_x(f_n: float, zeta: float, m: float) -> ModalStructure:
    """One mode in x only (Φ_yy = Φ_xy = 0)."""
    return ModalStructure(f_n=[f_n], zeta=[zeta], k=[m * (2 * np.pi * f_n) ** 2], shapes=[[1.0], [0.0]])


def test_insperger_stepan_slotting_minimum_depth():
    """Closed form of the ZOA limit for an SDOF in x, slotting (φ_st = 0, φ_ex = π).

    Mean x-force per unit depth and unit regenerative x-displacement: for a tooth at φ the
    chip grows by sin φ Δx, its forces K_t h (tangential) and K_n h (radial) project on x
    as −K_t sin φ cos φ − K_n sin² φ; averaged over a revolution with N teeth:
    A0_xx = (N/2π) ∫₀^π (−K_t sin φ cos φ − K_n sin² φ) dφ = −N K_n / 4
    (= N K_t α_xx / 4π with α_xx = −π K_r). With x = G F_x, G = R + iI, and
    Δx = (1 − e^{−iωT}) x the loop closes when 1 = a A0_xx G c, c = 1 − e^{−iωT}. Its
    imaginary part, Im(G c) = I (1 − cos ωT) + R sin ωT = 0, fixes T; then
    Re(G c) = R [(1 − cos ωT)² + sin² ωT] / (1 − cos ωT) = 2R, so
    a_lim(ω) = 1/(2 A0_xx R(ω)) = −2/(N K_n R(ω)), positive where R < 0.
    The smallest is at min R = −1/(4 k ζ (1 + ζ)) (at ω = ω_n √(1 + 2ζ)):
    a_min = 8 k ζ (1 + ζ) / (N K_n) ≈ 0.298 mm.
    """
    k = M_IS * (2 * np.pi * F_N_IS) ** 2
    a_min = 8 * k * ZETA_IS * (1 + ZETA_IS) / (N_IS * K_N_IS)
    assert a_min == pytest.approx(0.298e-3, abs=0.5e-6)
    f = np.arange(700.0, 1300.0, 0.05)
    rpm = np.linspace(5000.0, 22000.0, 2000)
    lobes = zoa_lobes(f, sdof_x(F_N_IS, ZETA_IS, M_IS).receptance(f), rpm, N_IS, K_T_IS,
                      K_N_IS / K_T_IS, 0.0, np.pi)
    assert lobes.min_depth == pytest.approx(a_min, rel=0.01)
    lowest = np.argmin(lobes.depth)
    assert lobes.chatter_frequency[lowest] == pytest.approx(F_N_IS * np.sqrt(1 + 2 * ZETA_IS), abs=0.2)
    assert np.all(np.isfinite(lobes.depth))
    assert np.all(lobes.depth >= a_min * (1 - 1e-6))


def averaged_directional_matrix(K_t: float, K_r: float, n_teeth: int, phi_st: float, phi_ex: float):
    """A0 (N/m² per unit depth) by Gauss–Legendre quadrature of the milling force model's
    tooth force (models.milling, Eqs. 6.1–6.5, κ = 90°) under unit regenerative Δx, Δy."""
    nodes, weights = np.polynomial.legendre.leggauss(64)
    phi = 0.5 * (phi_ex - phi_st) * nodes + 0.5 * (phi_ex + phi_st)
    K = CuttingCoefficients.shear_only(K_r, 0.0, K_t).as_array()
    columns = []
    for dx, dy in ((1.0, 0.0), (0.0, 1.0)):
        h = chip_thickness(phi, 0.0, np.pi / 2, dx, dy, 0.0)
        fx, fy, _ = tooth_force(phi, h, 1.0, np.pi / 2, K)
        columns.append([0.5 * (phi_ex - phi_st) * weights @ fx, 0.5 * (phi_ex - phi_st) * weights @ fy])
    return n_teeth / (2 * np.pi) * np.array(columns).T


@pytest.mark.parametrize("a_e, mode", [(0.012, "down"), (0.012, "up"), (0.012, "central"), (0.080, "down")])
def test_directional_matrix_matches_force_model(a_e, mode):
    phi_st, phi_ex = engagement_angles(a_e, 0.080, mode)
    K_t, K_r, n_teeth = 1889e6, 806.0 / 1889.0, 2
    expected = averaged_directional_matrix(K_t, K_r, n_teeth, phi_st, phi_ex)
    actual = n_teeth * K_t / (4 * np.pi) * directional_matrix(K_r, phi_st, phi_ex)
    np.testing.assert_allclose(actual, expected, rtol=1e-10, atol=1e-10 * np.abs(expected).max())


SMFE_XY = ModalStructure(
    f_n=[33.4, 57.4, 58.6], zeta=[0.061, 0.082, 0.029], k=[45.5e6, 32.1e6, 36.7e6],
    shapes=[[-0.055, 0.0199, 0.999], [0.6245, 0.9968, 0.0004]],
)
"""Tool side of the SMFE simulation, Table 6.2 / DIGEST §3b, x and y rows."""

ROTATED_PAIR = ModalStructure(
    f_n=[48.0, 61.0], zeta=[0.03, 0.04], k=[30e6, 40e6], shapes=[[0.8, -0.6], [0.6, 0.8]],
)
"""Two modes whose directions are 37° off the axes: strong Φ_xy."""


def direct_critical_depth(structure, rpm, n_teeth, A0, f_grid):
    """Smallest a > 0 (m) and its ω (Hz) with det(I − a (1 − e^{−iωT}) A0 Φ(ω)) = 0.

    The determinant is a quadratic in a; where one of its roots is nearly real and positive
    on a fine ω grid, (ω, a) is refined by fsolve on the real and imaginary parts of the
    determinant itself, with Φ evaluated at the exact ω.
    """
    T = 60.0 / (n_teeth * rpm)

    def matrix(f):
        return (1 - np.exp(-2j * np.pi * f * T))[:, None, None] * (A0 @ structure.receptance(f))

    M = matrix(f_grid)
    tr = M[:, 0, 0] + M[:, 1, 1]
    det = M[:, 0, 0] * M[:, 1, 1] - M[:, 0, 1] * M[:, 1, 0]
    disc = np.sqrt(tr**2 - 4 * det)
    roots = np.stack([(tr + disc) / (2 * det), (tr - disc) / (2 * det)], axis=1)
    skew = np.abs(roots.imag) / np.abs(roots)

    def equations(x):
        f, a_mm = x
        m = matrix(np.array([f]))[0]
        d = np.linalg.det(np.eye(2) - a_mm * 1e-3 * m)
        return [d.real, d.imag]

    solutions = []
    for col in range(2):
        s = skew[:, col]
        minima = np.nonzero((s[1:-1] < s[:-2]) & (s[1:-1] <= s[2:]) & (s[1:-1] < 0.05))[0] + 1
        for i in minima[roots[minima, col].real > 0]:
            x, info, ok, _ = fsolve(equations, [f_grid[i], roots[i, col].real * 1e3], full_output=True,
                                    xtol=1e-13)
            if ok == 1 and x[1] > 0 and np.hypot(*equations(x)) < 1e-10:
                solutions.append((x[1] * 1e-3, x[0]))
    return min(solutions)


@pytest.mark.parametrize(
    "structure, a_e, mode",
    [(SMFE_XY, 0.012, "down"), (ROTATED_PAIR, 0.040, "up"), (ROTATED_PAIR, 0.080, "down")],
)
def test_2d_lobes_with_cross_terms_match_direct_solution(structure, a_e, mode):
    n_teeth, K_t, K_r = 2, 1889e6, 806.0 / 1889.0
    phi_st, phi_ex = engagement_angles(a_e, 0.080, mode)
    f = np.arange(10.0, 200.0, 0.01)
    rpm = np.linspace(500.0, 1600.0, 2000)
    lobes = zoa_lobes(f, structure.receptance(f), rpm, n_teeth, K_t, K_r, phi_st, phi_ex)
    A0 = averaged_directional_matrix(K_t, K_r, n_teeth, phi_st, phi_ex)
    for i in (40, 500, 1000, 1500, 1960):
        depth, frequency = direct_critical_depth(structure, rpm[i], n_teeth, A0, np.arange(10.0, 200.0, 0.02))
        assert lobes.depth[i] == pytest.approx(depth, rel=5e-4), rpm[i]
        assert lobes.chatter_frequency[i] == pytest.approx(frequency, abs=0.05), rpm[i]


def test_rejects_a_receptance_of_the_wrong_shape():
    f = np.linspace(10.0, 100.0, 50)
    with pytest.raises(ValueError, match="Phi"):
        zoa_lobes(f, np.zeros((50, 3, 3)), np.linspace(500, 1500, 10), 2, 1e9, 0.4, 0.0, np.pi)
