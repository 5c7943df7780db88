"""The physics, written once: frames, earth, kinematics and the effect catalogue."""
