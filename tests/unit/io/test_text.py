"""A binary or non-UTF-8 file given as a CSV is reported by name (solderpyro.io.text and the
readers built on it), not as a bare UnicodeDecodeError."""

from __future__ import annotations

import codecs

import pytest

from solderpyro.io.measurements import read_measurements
from solderpyro.io.text import read_text

PNG = b"\x89PNG\r\n\x1a\n" + bytes(range(256))


def test_read_text_drops_the_bom_and_keeps_the_newlines(tmp_path):
    p = tmp_path / "a.csv"
    p.write_bytes(codecs.BOM_UTF8 + "a,b\r\n1,µ\n".encode())
    assert read_text(p) == "a,b\r\n1,µ\n"


@pytest.mark.parametrize("raw,byte,offset", [
    (PNG, "0x89", 0),  # a binary file
    (b"x,y\n1,2\n3,\xe9\n", "0xe9", 10),  # Latin-1, not UTF-8
    (codecs.BOM_UTF8 + b"x,y\n\xff", "0xff", 7),  # the offset counts the BOM
    ("x,y\n".encode("utf-16"), "0xff", 0),  # UTF-16 (its BOM)
    (b"x,y\n1,\x002\n", "0x00", 6),  # valid UTF-8, but a NUL byte: binary
])
def test_not_text_names_the_file_the_byte_and_its_offset(tmp_path, raw, byte, offset):
    p = tmp_path / "data.csv"
    p.write_bytes(raw)
    with pytest.raises(ValueError) as e:
        read_text(p, "SIM file")
    assert str(e.value).startswith(f"SIM file {p}: not a text file (byte {byte} at offset "
                                   f"{offset}")


def test_read_measurements_binary_file_names_it(tmp_path):
    p = tmp_path / "bin.csv"
    p.write_bytes(PNG)
    with pytest.raises(ValueError, match=r"bin\.csv: not a text file \(byte 0x89 at offset 0 "
                                         r"is not UTF-8\)"):
        read_measurements(p)
