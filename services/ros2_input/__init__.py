"""Live ROS 2 input (``sigmaslam ros2_input``): a robot's camera and IMU topics on Zenoh as the pipeline's sensors."""
