"""Digital twin sensor (issue #4): geometry, fisheye camera, physics backends, trajectories, effects, recorder."""
