"""ROS 2 recordings: twin's frames and shapes as a rosbag2-compatible MCAP file, and back.

One public face: :class:`McapRecorder` writes (:mod:`twin.io.rosbag.bag_writer`: topics, metadata, durability),
:class:`McapRecording` reads (:mod:`twin.io.rosbag.bag_reader`: damage rules), :mod:`twin.io.rosbag.ros_messages` holds
the message definitions and their batch CDR codecs. Needs the ``ros`` extra (``mcap``), imported when used.
"""

from twin.io.rosbag.bag_reader import MAGIC, McapRecording, is_mcap
from twin.io.rosbag.bag_writer import FORMAT, TOPICS, McapRecorder

__all__ = ["FORMAT", "MAGIC", "TOPICS", "McapRecorder", "McapRecording", "is_mcap"]
