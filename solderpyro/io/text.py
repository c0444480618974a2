"""Read a user's text file (a CSV) so that a binary or non-UTF-8 file is reported by name."""

from __future__ import annotations

import codecs
import os

__all__ = ["read_text"]


def read_text(path: str | os.PathLike[str], what: str = "") -> str:
    """The text of ``path`` decoded as UTF-8 (a leading byte-order mark dropped), newlines as
    in the file (read it as ``csv`` does, with ``newline=""``).

    Args:
        path: the file.
        what: a word put before the path in the message (e.g. ``"SIM file"``), or nothing.

    Raises:
        ValueError: ``"PATH: not a text file (byte 0x89 at offset 0 is not UTF-8)"`` for a
            binary file (a NUL byte) or one in another encoding, naming the file, the first
            bad byte and its offset. OSError: if it cannot be read.
    """
    with open(os.fspath(path), "rb") as fh:
        raw = fh.read()
    bom = len(codecs.BOM_UTF8) if raw.startswith(codecs.BOM_UTF8) else 0
    try:
        text = raw[bom:].decode("utf-8")
    except UnicodeDecodeError as e:
        at = bom + e.start  # the offset in the file
        raise _not_text(path, what, f"byte 0x{raw[at]:02x} at offset {at} is not UTF-8"
                        ) from None
    nul = raw.find(b"\x00")
    if nul >= 0:  # valid UTF-8 but binary (or UTF-16): no text CSV holds a NUL byte
        raise _not_text(path, what, f"byte 0x00 at offset {nul}")
    return text


def _not_text(path: str | os.PathLike[str], what: str, why: str) -> ValueError:
    name = f"{what} {os.fspath(path)}" if what else os.fspath(path)
    return ValueError(f"{name}: not a text file ({why}); a CSV saved as UTF-8 text is expected")
