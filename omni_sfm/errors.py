"""The one exception type that reaches users as a one-line message."""


class OmniSfmError(ValueError):
    """Bad input or an impossible request, explained in one line.

    The CLI prints ``omni-sfm: error: <message>`` and exits with code 2; library users catch it
    as a ``ValueError``. The message names the offending file, key or value and what is needed.
    """
