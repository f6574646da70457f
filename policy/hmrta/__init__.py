"""hmrta: heterogeneous multi-robot task allocation (core, no ROS)."""
__version__ = "0.1.0"
