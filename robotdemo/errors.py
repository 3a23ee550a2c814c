"""Errors the user can act on. Each carries a one-line message naming the file, object or value at fault;
the CLI prints it as ``robotdemo: error: <message>`` and exits non-zero instead of showing a traceback."""


class RobotDemoError(Exception):
    """Base class for errors reported to the user in one line."""


class AssetError(RobotDemoError):
    """A robot or scene description is missing or malformed."""


class SimulationError(RobotDemoError):
    """The physics diverged (NaN or inf in a state or a contact force) or was used wrongly."""
