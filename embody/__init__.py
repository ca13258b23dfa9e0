"""embody: offline pipeline from generated SMPL-X signing to validated robot joint trajectories.

The library (this package) has no Prefect import; orchestration lives in `tasks/` and `flows/`.
"""

__version__ = "0.1.0"
