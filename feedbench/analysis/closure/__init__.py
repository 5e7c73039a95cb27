"""Close the loop with measured data (issue 5): residual → missing effect → augmented model →
error before and after, on data the model was not fitted to.

Pure functions, arrays in, typed results out; the I/O (CSV + sidecar, EMPS .mat, HDF5
recordings, plots) lives in `feedbench.closure_io`, the command in `feedbench.commands.closure`.

- `trace`: `Trace` (a recording in SI) and `Kinematics` (zero-phase band-limited derivatives).
- `effects`: the vocabulary of terms and candidate effects (`LIBRARY`, `CANDIDATES`).
- `model`: `Model`, `Term`, variable-projection fit `fit_model`, `held_out_error`.
- `diagnosis`: `close_the_loop` — rank, add, refit, repeat.
- `spec`: `parse_model_config` — the TOML model config.
- `replay`: the model in closed loop with the recorded reference and excitation.
- `run`: `run_closure` — the whole pipeline; `report`: text and JSON.
"""

from feedbench.analysis.closure.diagnosis import ClosureOptions, ClosureResult, close_the_loop
from feedbench.analysis.closure.effects import CANDIDATES, EFFECTS, LIBRARY
from feedbench.analysis.closure.model import Fit, Model, Term, fit_model, held_out_error, new_term
from feedbench.analysis.closure.report import report_dict, report_text
from feedbench.analysis.closure.run import ClosureReport, run_closure
from feedbench.analysis.closure.spec import ControllerSpec, ModelSpec, parse_model_config
from feedbench.analysis.closure.trace import Kinematics, Trace, kinematics, nrmse

__all__ = [
    "CANDIDATES", "EFFECTS", "LIBRARY", "ClosureOptions", "ClosureReport", "ClosureResult",
    "ControllerSpec", "Fit", "Kinematics", "Model", "ModelSpec", "Term", "Trace",
    "close_the_loop", "fit_model", "held_out_error", "kinematics", "new_term", "nrmse",
    "parse_model_config", "report_dict", "report_text", "run_closure",
]
