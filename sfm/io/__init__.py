"""Files: COLMAP's database and models, the workspace's JSON files and run ledger, image files.

Everything graphsfm reads or writes goes through this room, and the conventions of the files
are applied here and nowhere else: pixel coordinates are shifted by 0.5 between graphsfm
(pixel centres at integers, OpenCV) and COLMAP (the image corner at 0, 0) when keypoints and
principal points are written or read (``sfm.io.pixel_convention``), and every file is written
under a temporary name and renamed into place, so an interrupted run never leaves half a file.

Storage: ``database.db`` is a SQLite file with COLMAP 4's schema (cameras, images, keypoints,
descriptors, matches, two_view_geometries, and the rigs and frames COLMAP 4 expects), blobs
typed as COLMAP types them and pair ids ``image_id1 * 2147483647 + image_id2`` with
``image_id1 < image_id2``.  A verified pair is a ``two_view_geometries`` row with config >= 2
and enough inliers (15 by default).  When a command exits the file is complete on its own (WAL
checkpointed), so COLMAP and pycolmap open it, pycolmap can map from exactly our matches (a
fair peer benchmark), and each stage resumes from what is already in it.  The stages after
matching need only the database: one written by ``graphsfm synth``, by COLMAP or by any tool
that follows the schema (keypoints with 2 columns, no descriptors, two-view geometries with
inlier matches but no E, F or H, images whose files are absent) is clustered, mapped and merged
like our own (points are then grey).

The workspace a run leaves (names in ``sfm.io.workspace``; the README lists every JSON key):

- ``database.db``: features, raw matches, verified two-view geometries.
- ``extract.json``: the camera each shared camera group got, so a resumed extraction reuses it.
- ``clusters.json``: the clusters (cores before expansion, members after), the MaxST and the
  options of the ``cluster`` stage.
- ``clusters/C<k>/<m>/``: local model ``m`` of cluster ``k`` (COLMAP binary, ``m = 0`` the
  largest).
- ``merge.json``: the cluster graph (similarities, MSD), each merge component's MinST, layers
  and anchor.
- ``sparse/N/``: the final models, largest first (COLMAP binary; ``graphsfm export`` writes
  text or PLY).
- ``report.json``: counts, per-stage wall times (``T_feat``, ``T_match``, ``T_GC``, ``T_SfM``,
  ``T_merge``, ``T_BA``), the executor and the workers that ran clusters, warnings.
- ``stages.json``: the run ledger (``sfm.io.ledger``).
- ``log.txt``: the run's log; ``recording.rrd``: the Rerun recording (``sfm.viz``).

Running again: the ledger records, for each stage, the options that decide its result and a
fingerprint of its input (by content, not time stamps).  A stage whose record matches is
skipped; one whose options or input changed runs again, and every later stage with it.
``extract`` and ``match`` also resume row by row (one transaction per image or batch of pairs),
and ``map`` cluster by cluster.  Options that change how a stage runs but not what it computes
(worker counts) are not recorded; the seed is.

Modules, in reading order:

- ``sfm.io.workspace``: the workspace's file names, atomic JSON writes, ``report.json``.
- ``sfm.io.ledger``: ``stages.json``, which results are current, options records, fingerprints.
- ``sfm.io.pixel_convention``: the 0.5 pixel shift at COLMAP's boundary.
- ``sfm.io.database_schema``: COLMAP 4's tables, id encodings, config codes and row records.
- ``sfm.io.database``: ``Database``, reading and writing those tables.
- ``sfm.io.colmap_model``: COLMAP sparse models (``.bin``, ``.txt``) to and from
  ``Reconstruction``, and PLY export.
- ``sfm.io.colmap_files``: the byte level of those model files.
- ``sfm.io.image_files``: finding images, decoding them upright to grey or RGB, masks.
- ``sfm.io.exif``: EXIF metadata: focal prior, GPS, orientation, make and model.
- ``sfm.io.options``: the options of ``graphsfm export``.

Paper: none directly; the database is the image graph's source (section 3.1.1) and the local
and final models are COLMAP's, as the paper's implementation (section 4.1) builds on COLMAP.
"""
