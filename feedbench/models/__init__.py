"""Physics shared by simulation and analysis: friction (Eq. 5.2), the two-mass axis and its
P-PI cascade (Ch. 4.2, 5.3), the rack-and-pinion axis (Ch. 3.2), structure, milling,
exciters and effects. One definition of each law; import each from its module
(`feedbench.models.axis`, `feedbench.models.friction`, …)."""
