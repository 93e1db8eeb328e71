"""Where a run's parallel tasks go: the executor and its workers."""

from __future__ import annotations

from dataclasses import dataclass

from sfm.core.options import OptionError, Options, option


@dataclass(frozen=True)
class ExecutionOptions(Options):
    """Where extraction, matching and the clusters' local SfM run (``--workers``, ``--executor``,
    ``--scheduler``)."""

    workers: int = option(0, "Worker processes on this machine (0: one per core); with Dask and no "
                          "scheduler, the size of the local Dask cluster.", min=0)
    executor: str = option("local", "Where the tasks run: a process pool on this machine, or a Dask "
                           "cluster (the dist extra).", choices=("local", "dask"))
    scheduler: str | None = option(None, "Address tcp://HOST:PORT of a running Dask scheduler (default: "
                                   "start a local Dask cluster).")

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.scheduler is not None and self.executor != "dask":
            raise OptionError("scheduler", "needs executor dask")


def make_executor(options: ExecutionOptions):
    """The executor ``options`` ask for (``sfm.execution.local``, ``sfm.execution.dask_cluster``);
    use it as a context manager so that a Dask cluster it starts is closed."""
    if options.executor == "dask":
        from sfm.execution.dask_cluster import DaskExecutor

        return DaskExecutor(options.scheduler, options.workers)
    from sfm.execution.local import LocalExecutor

    return LocalExecutor(options.workers)
