"""embody: offline pipeline from generated SMPL-X signing to validated robot joint trajectories.

The library (this package) has no Prefect import; orchestration lives in `tasks/` and `flows/`.
"""

from pathlib import Path

__version__ = "0.1.0"

#: Repository root of an editable install; `configs/` lives here.
PROJECT_ROOT = Path(__file__).resolve().parents[1]
