"""phalanx as a ROS 2 citizen (docs/ROS2.md): a fleet's robots published in rmw_zenoh's
own key space, so ROS 2 tools (RViz, Foxglove, `ros2 topic`) see them and can drive the
one that leads, and a finished run written as a rosbag2 MCAP file.

- `names`: ROS names and rmw_zenoh's key expressions (data keys, liveliness tokens);
- `topics`: which ROS topics a fleet has, their types and QoS, one list for the bridge,
  the export and the access rules;
- `typestore`: ROS 2 message types, RIHS01 type hashes and CDR, from `rosbags`;
- `messages`: phalanx's values as ROS 2 messages;
- `graph`: a node in the ROS graph over a Zenoh session (tokens, publishers, attachments,
  subscriptions);
- `bridge`: the process behind `phalanx ros2` (the fleet out, `cmd_vel` and `goal_pose` in);
- `export`: a results folder as rosbag2 MCAP (`phalanx export --mcap`).

`rosbags` is an optional dependency (the `ros2` extra): it is imported only when one of
these is used, never when phalanx is imported.
"""
