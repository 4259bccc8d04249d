"""From the answer to a policy: a graft cell exported as a LeRobot checkpoint folder that
LeRobot's own tools load and train, through the `lerobot_policy_graft` plugin
(plugins/lerobot_policy_graft).

`python -m bench.export CELL_ID --results-dir DIR --out OUT` (or `--best BACKBONE SUITE`).
locate.py finds and checks the cell (one line per bad input), build.py writes the folder
(whole or not at all), card.py its README.md.
"""

from bench.export.build import export_cell  # noqa: F401
from bench.export.locate import ExportError, best_cell  # noqa: F401
