"""World builders for physics engines, shared by the synthetic reality and by model agents.

A builder turns the twin's descriptions (a robot's URDF, entity shapes of :mod:`protocol.geometry`,
friction) into one engine's world. It holds no policy of its own: gains, friction and contact
softness are arguments, so that a model agent and the reality can build different worlds with it.
Builders depend on numpy, the engine and :mod:`protocol` only (never on the conductor).

- :mod:`agents.engines.mujoco_world`: MuJoCo (MjSpec) worlds of a robot arm on a table.
"""
