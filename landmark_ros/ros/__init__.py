"""Everything that knows ROS message types: codec, schemas, QoS, parameters, runner."""
