"""Recordings on disk, whatever container ROS wrote them in.

``recording`` (one recording: an MCAP file or a bag), ``layout`` (where its bytes are),
``mcap`` (streaming MCAP reading), ``mcap_index`` (a few messages through the index),
``mcap_write`` (the one ROS 2 MCAP writer), ``rosbags`` (rosbag2 ``.db3`` and ROS 1
``.bag``).

And vtcal's own files: ``artefacts`` (the declared Parquet schemas, checked on
write and read), ``fileio`` (atomic writes, file and config hashes), ``jsonio``
(the JSON side files' one byte-stable form), ``resources`` (where the schemas,
report templates and the spec are), ``tables`` (a user's CSV or Parquet tables),
``run_folder`` (the files of a run folder: names, schemas, writers).

And the forms vtcal reads and writes as text: ``known_distances`` (a recording's
``known_distances`` metadata and ``--distance``: ``A:B=METRES``), ``numfmt`` (numbers
as the HTML pages show them).
"""
