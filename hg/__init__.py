"""haptic-glance: reinforcement-learned tactile probing for 3D object recognition."""
