"""Recordings on disk, whatever container ROS wrote them in.

``recording`` (one recording: an MCAP file or a bag), ``layout`` (where its bytes are),
``mcap`` (streaming MCAP reading), ``mcap_index`` (a few messages through the index),
``mcap_write`` (the one ROS 2 MCAP writer), ``rosbags`` (rosbag2 ``.db3`` and ROS 1
``.bag``).
"""
