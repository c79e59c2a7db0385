"""Hostile XML into the importers (vigproc.stores.xmlsafe, used by the LCP and lensfun
readers): a DTD is refused in any encoding (checked after decoding), every file is capped by
size before it is read and by its element count while it is parsed (issue 37)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from conftest import run_cli
from test_lcp import HEAD, TAIL, entry_attrs
from vigproc.errors import ModelError
from vigproc.stores import xmlsafe
from vigproc.stores.lcp import LcpError, read_lcp
from vigproc.stores.lensfun import MAX_DB_FILE_BYTES, bundled_db_dir, load_lenses

DTD = '<!DOCTYPE x [<!ENTITY lens "Evil Lens">]>'


@pytest.mark.parametrize("codec, bom", [("utf-16-le", b"\xff\xfe"), ("utf-16-be", b"\xfe\xff"),
                                        ("utf-16-le", b""), ("utf-32-le", b"\xff\xfe\x00\x00"),
                                        ("utf-8", b"\xef\xbb\xbf")])
def test_a_dtd_is_refused_in_any_encoding_and_the_profile_read_without_one(tmp_path, codec, bom):
    name = codec.replace("-le", "").replace("-be", "").upper()
    good = HEAD.replace('encoding="UTF-8"', f'encoding="{name}"') + entry_attrs() + TAIL
    bad = good.replace("<x:xmpmeta", DTD + "<x:xmpmeta", 1).replace("EF35mm f/1.4L USM", "&lens;")
    (tmp_path / "good.lcp").write_bytes(bom + good.encode(codec))
    (tmp_path / "bad.lcp").write_bytes(bom + bad.encode(codec))
    entries, _ = read_lcp(tmp_path / "good.lcp")
    assert len(entries) == 1 and entries[0].lens == "EF35mm f/1.4L USM"
    with pytest.raises(LcpError, match="DTD or entity declaration is not allowed"):
        read_lcp(tmp_path / "bad.lcp")


def test_encoding_declarations_are_followed(tmp_path):
    text = HEAD.replace('encoding="UTF-8"', 'encoding="ISO-8859-1"') + entry_attrs(
        identity={"Make": "Caf\u00e9", "Lens": "L\u00e9ns"}) + TAIL
    (tmp_path / "latin1.lcp").write_bytes(text.encode("latin-1"))
    entries, _ = read_lcp(tmp_path / "latin1.lcp")
    assert entries[0].lens == "L\u00e9ns"
    (tmp_path / "lying.lcp").write_bytes(HEAD.encode() + b"\xff\xfe" + TAIL.encode())  # says UTF-8, is not
    with pytest.raises(LcpError, match="cannot decode"):
        read_lcp(tmp_path / "lying.lcp")
    (tmp_path / "unknown.lcp").write_bytes(HEAD.replace("UTF-8", "X-NOPE").encode() + TAIL.encode())
    with pytest.raises(LcpError, match="unknown encoding"):
        read_lcp(tmp_path / "unknown.lcp")


def test_too_many_elements_are_refused_while_parsing():
    raw = b"<x>" + b"<a/>" * 2000 + b"</x>"
    assert len(list(xmlsafe.parse_xml(raw, ValueError, "f", "file", max_elements=2001))) == 2000
    with pytest.raises(ValueError, match="more than 1000 XML elements"):
        xmlsafe.parse_xml(raw, ValueError, "f", "file", max_elements=1000)


def test_a_lensfun_database_is_refused_by_size_before_parsing(tmp_path):
    big = tmp_path / "huge.xml"
    with open(big, "wb") as fh:  # 100 MB, sparse: nothing of it is ever read
        fh.truncate(100 << 20)
    with pytest.raises(ModelError, match="too large for a lensfun database file"):
        load_lenses([big])
    dtd = tmp_path / "dtd.xml"
    dtd.write_bytes(('<lensdatabase>' + DTD + '</lensdatabase>').encode("utf-16"))
    with pytest.raises(ModelError, match="DTD or entity"):
        load_lenses([dtd])
    # lensfun's own database stays within the caps, with room to spare
    sizes = [p.stat().st_size for p in bundled_db_dir().glob("*.xml")]
    assert sizes and max(sizes) * 4 < MAX_DB_FILE_BYTES


def test_the_fit_lens_family_command_refuses_a_huge_database_quickly_and_clearly(tmp_path):
    big = tmp_path / "huge.xml"
    with open(big, "wb") as fh:
        fh.truncate(100 << 20)
    r = run_cli("prior", "fit-lens-family", "--db", big, "-o", tmp_path / "fam.json")  # in this process
    assert r.returncode != 0 and "too large for a lensfun database file" in r.stderr
    assert "Traceback" not in r.stderr and not (tmp_path / "fam.json").exists()
