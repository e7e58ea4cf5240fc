"""ROS 2 messages and rmw_zenoh's wire conventions, sans-I/O.

Bytes in, typed values or one :class:`~protocol.errors.ProtocolError` out, as in the rest
of :mod:`protocol`. CDR and the RIHS01 type hashes come from ``rosbags`` (a pure-Python
implementation of ROS 2's type system and serialisation) rather than from code of ours:

- :mod:`protocol.ros2.types`: the type store, DDS type names and per-distro type hashes;
- :mod:`protocol.ros2.keys`: rmw_zenoh's data keys and liveliness tokens, and the bare keys
  of zenoh-bridge-ros2dds;
- :mod:`protocol.ros2.attachment`: the 33-byte attachment rmw_zenoh puts on every sample;
- :mod:`protocol.ros2.occupancy`: ``nav_msgs/msg/OccupancyGrid`` <-> :class:`pgvd.grid.Grid`,
  and the ``tf2_msgs/msg/TFMessage`` that places each robot's map in the merged frame;
- :mod:`protocol.ros2.markers`: ``visualization_msgs/msg/MarkerArray`` of line lists, which
  RViz draws with no code (the links between robots' maps).
"""
