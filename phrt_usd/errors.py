"""Domain errors: anything the user can fix (bad stage, bad option) is a ``PhrtError``.

The CLI prints ``str(error)`` as one line and exits non-zero; it never shows a traceback
for these. Messages say what is wrong and where: prim path, attribute, frame.
"""


class PhrtError(Exception):
    """A problem with the user's input, reported as one line."""


class BadOption(PhrtError):
    """An option value out of its range or malformed (the CLI exits 2)."""
