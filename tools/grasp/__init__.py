"""Robot-hand tools (extra `[hand]`): fingertip pose selection on a hand URDF (seed §III.N), the
thumb–index contact graph and the selective grasp closed through the sensor runtime (seed §V-B)."""
