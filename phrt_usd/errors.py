"""Domain errors: anything the user can fix (bad stage, bad option) is a ``PhrtError``.

The CLI prints ``str(error)`` as one line and exits non-zero; it never shows a traceback
for these. Messages say what is wrong and where: prim path, attribute, frame.
"""

import re


class PhrtError(Exception):
    """A problem with the user's input, reported as one line."""


class BadOption(PhrtError):
    """An option value out of its range or malformed (the CLI exits 2)."""


class UnreadableInput(PhrtError):
    """The input cannot be read or used at all: a missing, damaged or non-USD file, or
    stage metadata nothing can be measured in (the CLI exits 2)."""


#: The reason given when USD's own quotes bytes that are not UTF-8 (Python cannot
#: decode it): the parser stopped at damaged text.
NOT_UTF8_REASON = "USD's reason quotes bytes that are not UTF-8 text"
#: USD's reasons that only repeat that a layer failed, after the reason it failed.
_REPEATS = ("Failed to open layer",)
#: A parser's location: ``<file>:<line>:<column>: `` (the sdf text parser's form).
_LOCATED = re.compile(r"\S:\d+:\d+: ")


def usd_error_reason(exc: Exception) -> str:
    """One line from a (multi-line) USD ``Tf.ErrorException``: the reason of the error
    USD posted first, preferring one that names its ``file:line:column`` (the sdf text
    parser posts the same error with and without its location). Reasons come from each
    ``Tf.Error``'s ``commentary``; text that is not a ``Tf.ErrorException`` is read as
    ``Error in '<function>' at line N in file F : '<reason>'`` lines."""
    reasons = [_one_line(r) for r in _reasons(exc)]
    reasons = [r for r in reasons if r and not r.startswith(_REPEATS)]
    located = [r for r in reasons if _LOCATED.search(r)]
    if located or reasons:
        return (located or reasons)[0]
    return "unreadable, or not a valid USD file"


def _reasons(exc: Exception) -> list[str]:
    """The reasons a USD error gives, in the order USD posted them."""
    found = []
    for arg in getattr(exc, "args", ()):
        try:
            found.append(str(arg.commentary))
        except AttributeError:  # not a Tf.Error: a plain message
            continue
        except UnicodeDecodeError:  # USD quotes the damaged bytes it could not parse
            found.append(NOT_UTF8_REASON)
    if found:
        return found
    try:
        text = str(exc)
    except UnicodeDecodeError:
        return [NOT_UTF8_REASON]
    return re.findall(r" : '(.*?)'\s*(?=\n\s*Error in |\Z)", text, flags=re.DOTALL)


def _one_line(text: str) -> str:
    return " ".join(text.split())
