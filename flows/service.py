"""A local process a run or a test starts (a Dask cluster, a PostgreSQL server) and must stop."""

from __future__ import annotations


class LocalService:
    """`with Service(...) as address:` starts it, and stops it even when the start fails half way
    (a scheduler up, a worker not), so nothing it started outlives the block."""

    def start(self) -> str:
        raise NotImplementedError

    def stop(self) -> None:
        raise NotImplementedError

    def __enter__(self) -> str:
        try:
            return self.start()
        except BaseException:
            self.stop()
            raise

    def __exit__(self, *exc: object) -> None:
        self.stop()
