"""robotdemo: a robot that sorts objects by touching them (scene, robot, state machine, demo, CLI)."""

__version__ = "0.1.0"
