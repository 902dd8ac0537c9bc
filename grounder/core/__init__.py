"""What every stage of grounder reads and writes: recorded motion and the files users hand us.

- `trajectory`: the trajectory format (a folder of ``.npz`` files), its checks against a MuJoCo model.
- `importers`: other projects' recordings converted to it (the DAIR-PLL cube tosses).
- `repeats`: trajectories that record the same motion twice, and splits that keep such copies together.
- `json_files`, `torch_files`: reading JSON and torch files of unknown origin safely, with errors a user can act on.
- `html_report`: self-contained HTML reports (figures embedded), written whole or not at all.
"""

from grounder.core.html_report import Section, figure_to_data_uri, render_html, write_html_report
from grounder.core.importers import import_trajectories, load_dair_pll_cube
from grounder.core.json_files import read_json_file
from grounder.core.torch_files import load_weights_file
from grounder.core.trajectory import (
    Trajectory,
    load_trajectories,
    load_trajectory,
    save_trajectories,
    save_trajectory,
    validate_against_model,
)

__all__ = [
    "Section",
    "Trajectory",
    "figure_to_data_uri",
    "import_trajectories",
    "load_dair_pll_cube",
    "load_trajectories",
    "load_trajectory",
    "load_weights_file",
    "read_json_file",
    "render_html",
    "save_trajectories",
    "save_trajectory",
    "validate_against_model",
    "write_html_report",
]
