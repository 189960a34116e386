"""Domain errors: anything the user can fix (bad stage, bad option) is a ``PhrtError``.

The CLI prints ``str(error)`` as one line and exits non-zero; it never shows a traceback
for these. Messages say what is wrong and where: prim path, attribute, frame.
"""

import re


class PhrtError(Exception):
    """A problem with the user's input, reported as one line."""


class BadOption(PhrtError):
    """An option value out of its range or malformed (the CLI exits 2)."""


def usd_error_reason(exc: Exception) -> str:
    """One line from a (multi-line) USD ``Tf.ErrorException``: its first quoted reason
    (USD's text is ``Error in '<function>' at line N in file F : '<reason>'``)."""
    try:
        text = str(exc)
    except UnicodeDecodeError:  # USD quotes the damaged bytes it could not parse
        text = ""
    found = re.findall(r"'([^'\n]+)'\s*$", text, flags=re.MULTILINE)
    causes = [c.strip() for c in found if not c.startswith("Failed to open layer")]
    if causes:
        return causes[0]
    return "unreadable, or not a valid USD file"
