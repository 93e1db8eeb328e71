"""The stages: one function per step of the pipeline, the only code that writes the workspace.

Each stage is a function ``run_<stage>(..., workspace, options, ...) -> result`` that reads
its input from the workspace (the image folder, ``database.db``, ``clusters.json``, the local
models), calls the rooms below it for the work (they never write the workspace) and writes
its output back, with its options and input recorded in the run ledger.  The command line
(``sfm.cli``) and the Python API (``sfm.api``) only build options and call these functions.

Design:

- The pipeline (paper Figure 1): ``extract`` -> ``match`` -> ``cluster`` -> ``map`` ->
  ``merge``; ``reconstruct`` runs them all in order with every stage's options, one executor
  and one recording.  ``synth`` and ``demo`` make workspaces with exact ground truth.
- The database is the single source of truth between stages: ``cluster``, ``map`` and
  ``merge`` need only ``database.db`` (and each other's files), so a database written by
  ``synth`` or by COLMAP enters the pipeline at ``cluster``.  Without ``clusters.json``, or with
  one cluster, ``map``'s models are the final ones (``sparse/N``) and nothing is merged; with
  several, ``map`` writes ``clusters/C<k>/<m>`` and ``merge`` writes ``sparse/N``.
- Rerunning is resuming: a stage whose options and input match its ledger record is skipped;
  ``extract`` and ``match`` skip the images and pairs already in the database, ``map`` the
  clusters already done; a stage that runs again makes every later one run again
  (``sfm.io.ledger``).  Every file is written atomically, the database one transaction per
  image or batch of pairs, so a killed run loses only the work in flight.
- Parallel tasks go to an executor (``sfm.execution``); the tasks return arrays and models,
  and only the stage, in the calling process, writes them.  Results are written in a fixed
  order and randomness comes from the seed, so the same input, options and seed give the same
  files with any number of workers.
- Errors a user sees are one line with an exit code (``sfm.errors``): bad input is
  ``InputError`` (2), input from which no model can be made ``NoModelError`` (3); a partial
  result (a failed cluster, a scene in several parts) is a warning in ``report.json``.

Modules, in reading order:

- ``sfm.stages.reconstruct``: ``reconstruct``, every stage in order, and ``ReconstructOptions``.
- ``sfm.stages.extract``: ``run_extract``: images -> cameras, keypoints, descriptors.
- ``sfm.stages.extract_writer``: where ``extract`` writes (database rows, ``extract.json``).
- ``sfm.stages.match``: ``run_match``: pairs -> raw matches and two-view geometries.
- ``sfm.stages.cluster``: ``run_cluster``: the image graph -> ``clusters.json``.
- ``sfm.stages.payloads``: one cluster's payload read from the database, when it is needed.
- ``sfm.stages.map``: ``run_map``: local incremental SfM of every cluster, in parallel.
- ``sfm.stages.merge``: ``run_merge``: local models -> merged, refined models, ``merge.json``.
- ``sfm.stages.extend``: ``run_extend``: new photos added to the finished ``sparse/0`` as new
  clusters merged into it (extract, match, cluster, map, merge of the new part; its own ledger
  entry, ``WORK/extend/``).
- ``sfm.stages.synth``: ``run_synth``: a synthetic scene as a new workspace.
- ``sfm.stages.demo``: ``run_demo``: the rendered scene reconstructed and evaluated.

Paper: Figure 1 (the pipeline); ``cluster`` section 3.1 and Algorithm 1, ``map`` section 3.2,
``merge`` section 3.2 and Algorithm 2 (see ``sfm.clustering``, ``sfm.mapper``, ``sfm.merge``).
"""
