"""ROS 2 on Zenoh: rmw_zenoh's formats (graph.py, types.py) and the bridge that makes every
served map a ROS 2 node (bridge.py), enabled by the ``[ros2]`` config section (conf.py).

Only conf.py is imported by the service unless the section is enabled; the rest needs the
``ros2`` extra (rosbags, xxhash)."""
