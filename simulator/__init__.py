"""The simulated world: P3DX kinematics, obstacles, sonar, collisions, scripted events."""
