"""ROS 2 interop without ROS: CDR messages, rmw_zenoh key expressions and tokens, ROS 2 MCAP files.

Pure library code (no bus inside): ``msgs`` (message models, CDR encode/decode), ``rmw`` (rmw_zenoh
naming and attachments), ``config`` (the typed settings), ``convert`` (twohr <-> ROS messages) and
``bag`` (the ``ros2``-profile MCAP writer).
"""
