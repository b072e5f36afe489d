"""Arena: a robot-control server. One master per robot, many slaves, safety first."""

__version__ = "0.1.0"
