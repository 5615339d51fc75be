"""bcrl-convert: recorded demonstrations (ROS 1/2 bags, robomimic HDF5) -> LeRobotDataset v3."""
