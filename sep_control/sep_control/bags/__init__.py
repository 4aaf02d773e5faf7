"""Recorded rosbag2 bags of the topic graph (docs/reference/topics.md): reading, analysis, report.

storage     raw rosbag2 reading (MCAP, sqlite3), truncated-bag recovery: `read_raw`, `BagError`
messages    decoding the contract messages (topic keys, stamps, payload parsers)
reader      a bag of one episode as arrays: `read_episode` -> `Episode`
repair      rewriting a truncated bag as a complete one: `repair_bag`
writer      the recorder's ROS-free bag writer thread: `BagSink`
bag_metrics the metrics of one episode from its arrays, and pooled over many: `episode_metrics`, `pooled_metrics`
analysis    metrics of one or many bags: `analyze`, `aggregate`
figures     the report's PNG figures (matplotlib)
report      report.md: `write_report`

Nothing here imports rclpy; the recorder node is `sep_control.ros.record_node`.
"""
