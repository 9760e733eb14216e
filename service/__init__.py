"""dqpose: average, fuse and interpolate rigid poses with dual quaternions."""
__version__ = "0.1.0"
