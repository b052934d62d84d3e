"""Where the radar was: trajectories and phase centres, and what a tracker gets wrong about them."""
