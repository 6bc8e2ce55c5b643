"""Deployment on a Unitree G1: the exported policy over the robot's low-level DDS interface.

`transport` speaks `unitree_hg` LowCmd_/LowState_ through CycloneDDS, `crc` signs and checks them,
`motors` maps the policy's 27 joints onto the G1's 29 motors, `safety` holds the modes and the
watchdog, `odometry` the pluggable position input, `controller` the 50 Hz loop (`adamimic deploy`)
and `bridge` a MuJoCo G1 that stands in for the robot (`adamimic sim-bridge`).
"""
