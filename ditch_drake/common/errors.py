"""The errors a user can cause, in one neutral module that every layer may import.

The command line turns each of them into exit code 2 and one message (`ditch-drake: error:
...`) naming the bad value and what was expected; anything else is a bug and keeps its
traceback.
"""


class ConfigError(ValueError):
    """A configuration file or value is malformed or out of range."""


class TerrainError(ValueError):
    """A terrain parameter is out of its allowed range."""


class ResultsError(ValueError):
    """A results file that cannot be read as this schema and version."""


class DatasetError(ValueError):
    """A demonstration file is missing, corrupt, or not what the schema says."""


class CheckpointError(ValueError):
    """A file that is not a readable checkpoint of the expected schema and version."""


class CheckpointNotFoundError(CheckpointError, FileNotFoundError):
    """No checkpoint file at a path: nothing there, or a folder.

    Both a `CheckpointError` (the command line turns it into a message) and a
    `FileNotFoundError` (what callers that test for a missing file catch).
    """
