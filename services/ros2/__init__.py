"""The ROS 2 face (``sigmaslam ros2``): sigmaslam's results as ROS 2 topics on Zenoh in rmw_zenoh's wire format."""
