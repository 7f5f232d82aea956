"""dbml as a ROS 2 package: its executables run the dbml Python package over rclpy."""
