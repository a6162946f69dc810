"""Code that runs on a robot: the HAL, the behaviours, the agent process and the KheperaIV driver.

Depends only on the standard library, numpy, pyzmq, pyyaml and filterpy, and keeps Python 3.9 syntax.
Nothing here may import ``sim_backend`` or ``hub`` (a test enforces it).
"""
