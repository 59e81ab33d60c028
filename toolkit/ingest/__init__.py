"""Real recordings in: the ``ingest`` stage and what it is made of.

- ``recording``: the ``Recording`` a reader returns (indexed, not loaded) and ``IngestError``.
- ``sync``: time synchronisation with a tolerance, stamp checks, decimation (pure numpy).
- ``convert``: streaming, resumable conversion of a ``Recording`` into a sequence folder.
- ``stage``: the recipe stage ``ingest`` (source: rosbag | tum_rgbd | carmen | sequence).

Readers live in ``toolkit.io`` (``rosbag``, ``tum_rgbd``, ``carmen_ingest``). This package
imports none of them at import time, so ``import toolkit.ingest`` stays cheap.
"""
