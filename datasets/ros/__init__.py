"""ROS1 / ROS2 bags through ``rosbags``: readers, writers, message definitions, old-bag fallbacks.

========================  ===========================================================================
module                    holds
========================  ===========================================================================
``typestores``            the ROS1 / ROS2 type stores (standard + ``grid_map_msgs``), message helpers
``bag``                   opening a bag (ROS1 / ROS2 / damaged ROS1) behind one small interface
``chunkscan``             reading a ROS1 bag whose index is damaged by scanning its chunks
``reader``                ``read_ros1`` / ``read_ros2``: a bag to a :class:`~datasets.types.Recording`
``writer``                ``write_recording``, ``open_bag_writer``, ``write_messages``
========================  ===========================================================================

:mod:`datasets.rosbag` re-exports the public functions (the registry's entry points).
"""
