"""Where a stage's independent tasks run: a process pool on this machine, or a Dask cluster.

Three stages have independent tasks: ``extract`` (one per image), ``match`` (one per batch of
pairs) and ``map`` (one per cluster: the paper's "local SfM solvers are executed in parallel or
distributed mode").  Each hands a task function and its items to an executor's ``map``; the
executor decides where they run.  ``--workers`` sets the worker processes of every stage, and
``--executor dask`` (with ``--scheduler tcp://HOST:PORT``, or a local Dask cluster) sends the
same tasks to other machines.

Design:

- A task is a pure function of data: a cluster's payload (``sfm.mapper.payload``) holds its
  images' names, camera priors, keypoints and verified matches, never a path into the caller's
  disk, and a remote worker gets image bytes and feature arrays instead of file names
  (``remote`` tells a stage which it needs).  Results come back to the caller, which alone
  writes the workspace, so no shared filesystem is needed.
- Results come in input order when the caller writes them in order (extraction and matching:
  the same files with any number of workers) or as tasks finish (clusters).  At most two tasks
  per worker are in flight, so lazily built items are built when a worker is about to need
  them.  A task that raises either stops the map or is reported with its error (a failed
  cluster must not stop the others).
- Each worker runs one task at a time with OpenCV's and BLAS's threads limited to one: the
  parallelism is across processes.  Local pools fork from one server process that has imported
  the pipeline already (``forkserver``).
- Failures are Dask's business, not a loop of ours: a task whose worker dies is rescheduled, a
  task that raises is retried once.  No RPC, scheduler or retry loop is written here.

Modules, in reading order:

- ``sfm.execution.options``: ``ExecutionOptions`` and ``make_executor``.
- ``sfm.execution.local``: ``LocalExecutor``, ``TaskResult``, single-threaded workers.
- ``sfm.execution.process_pool``: the start method of the local pools (forkserver, preload), one
  thread per worker.
- ``sfm.execution.spare_cores``: a task run in this process hands a piece of its work to an idle core.
- ``sfm.execution.dask_cluster``: ``DaskExecutor``, the same ``map`` on a Dask cluster.

Paper: section 3.2 and the abstract's "image clusters are distributed into servers to execute
SfM in parallel mode".
"""
