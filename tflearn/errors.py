"""The one family of errors that bad input raises.

Every problem with what a user hands tflearn — a config file or override, a motion
file, a basis.json, a checkpoint, a motion name — is an :class:`InputError` whose message
names the file (or key, or name) and the problem. The command line reports these as one
line and exit status 2; anything else is a bug in tflearn and keeps its traceback.
"""


class InputError(ValueError):
    """Bad input; the message names where and what."""
