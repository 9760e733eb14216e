"""Device drivers (arms, pose sources) and their simulators."""
