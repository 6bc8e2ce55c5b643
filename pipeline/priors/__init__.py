"""priors: what the env's zero action does before a policy learns anything.

`open_loop` rolls out and searches open-loop jumps of the G1; `push_prior` turns the furthest one that
passes the env's fall checks into a per-ψ push added to the feedforward zero action.
"""
