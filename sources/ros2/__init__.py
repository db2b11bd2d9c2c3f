"""ROS 2 as a source of frames: rmw_zenoh keys and attachments (``keys``), CDR messages (``messages``), pairing
colour and depth topics into frames (``pairing``) and rosbag2 recordings (``rosbag``). Pure: no zenoh, no threads;
``service`` wires these to zenoh. The submodules are imported by name (this package imports nothing, so
``sources`` opens other datasets without loading rosbags)."""
