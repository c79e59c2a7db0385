"""Hostile XML, read safely: the importers' (Adobe LCP, lensfun) one way in.

A file is refused by its size before it is read (:func:`read_capped`), decoded by what
it says it is (a byte-order mark, else an encoding declaration, else UTF-8; UTF-16 and
UTF-32 without a mark are recognised by their ``<`` ``?`` bytes), and only then looked at for a
document type or entity declaration (:func:`parse_xml`): a check on the raw bytes lets
a UTF-16 file, whose ``<!DOCTYPE`` is spelt with zero bytes between the letters,
through. What is parsed is the decoded text, re-encoded as UTF-8 without its
declaration, so the parser sees exactly the text that was checked.
"""

from __future__ import annotations

import codecs
import os
import re
import stat
import xml.etree.ElementTree as ET

from vigproc.errors import one_line

__all__ = ["MAX_ELEMENTS", "decode_xml", "parse_xml", "read_capped"]

#: Most elements parsed from one file (lensfun's largest file has 7 252; an LCP of 10 000
#: entries about 200 000): with the size cap, this bounds the parser's memory whatever the
#: file is made of (16 MB of ``<a/>`` would be 4 million elements, 0.5 GB).
MAX_ELEMENTS = 500_000
_CHUNK = 1 << 20

# (mark, codec): the longest marks first (UTF-32 LE's starts like UTF-16 LE's)
_BOMS = ((codecs.BOM_UTF32_LE, "utf-32-le"), (codecs.BOM_UTF32_BE, "utf-32-be"), (codecs.BOM_UTF8, "utf-8"),
         (codecs.BOM_UTF16_LE, "utf-16-le"), (codecs.BOM_UTF16_BE, "utf-16-be"))
# "<?" in an encoding without a mark (XML 1.0, appendix F)
_UNMARKED = ((b"<\0\0\0?\0\0\0", "utf-32-le"), (b"\0\0\0<\0\0\0?", "utf-32-be"), (b"<\0?\0", "utf-16-le"),
             (b"\0<\0?", "utf-16-be"))
_DECLARATION = re.compile(r"^\s*<\?xml\b[^>]*?\?>", re.S)
_ENCODING = re.compile(rb"""^\s*<\?xml\b[^>]*?\bencoding\s*=\s*["']([A-Za-z][A-Za-z0-9._-]{0,39})["']""", re.S)
# any declaration of a document type or entity, however spaced or cased
_DTD = re.compile(r"<!\s*(DOCTYPE|ENTITY|ELEMENT|ATTLIST|NOTATION)", re.I)


def read_capped(path: str | os.PathLike[str], limit: int, error: type[Exception], what: str) -> bytes:
    """The bytes of the regular file ``path``, refused by size (stat, then a read of at
    most ``limit + 1`` bytes for a file that grows) before anything is parsed.

    Parameters
    ----------
    path : path-like
    limit : int
        Largest size accepted, in bytes.
    error : type
        The typed error to raise (one argument: the message).
    what : str
        What the file is, for the message (``lens profile``, ``lensfun database file``).

    Returns
    -------
    bytes

    Raises
    ------
    error
        Not a regular file, larger than ``limit``, or unreadable.
    """
    where = os.fspath(path)
    try:
        st = os.stat(path)
        if not stat.S_ISREG(st.st_mode):  # a FIFO or device would block or never end
            raise error(one_line(f"{where}: not a regular file"))
        if st.st_size > limit:
            raise error(one_line(f"{where}: {st.st_size} bytes is too large for a {what} (limit {limit})"))
        with open(path, "rb") as fh:
            raw = fh.read(limit + 1)
    except OSError as exc:
        raise error(one_line(f"cannot read {what} {where}: {exc.strerror or exc}")) from None
    if len(raw) > limit:
        raise error(one_line(f"{where}: more than {limit} bytes is too large for a {what} (it grew)"))
    return raw


def decode_xml(raw: bytes) -> str:
    """The text of the XML document ``raw``: decoded by its byte-order mark, else by the
    ``<?`` of an unmarked UTF-16/32, else by its encoding declaration, else as UTF-8.

    Raises
    ------
    ValueError
        An unknown encoding, or bytes that are not in the encoding the file names.
    """
    codec = next((c for bom, c in _BOMS if raw.startswith(bom)), None)
    if codec is not None:
        raw = raw[len(next(b for b, c in _BOMS if c == codec)):]
    else:
        codec = next((c for start, c in _UNMARKED if raw.startswith(start)), None)
    if codec is None:
        m = _ENCODING.match(raw)
        codec = m.group(1).decode("ascii") if m else "utf-8"
        try:
            if codecs.lookup(codec).name in ("utf-16", "utf-32"):  # named so but one byte a letter
                raise ValueError(f"says {codec} but is not")
        except LookupError:
            raise ValueError(f"unknown encoding {codec!r}") from None
    try:
        return raw.decode(codec)
    except UnicodeDecodeError as exc:
        raise ValueError(f"not {codec} text (byte {exc.start})") from None


def parse_xml(raw: bytes, error: type[Exception], where: str, what: str,
              max_elements: int = MAX_ELEMENTS) -> ET.Element:
    """Parse hostile XML: decoded first (:func:`decode_xml`), a document type or entity
    declaration refused in the decoded text, then the text parsed as UTF-8.

    Parameters
    ----------
    raw : bytes
        The file's bytes (size-capped by :func:`read_capped`).
    error : type
        The typed error to raise.
    where : str
        The file's name, for the message.
    what : str
        What the file is, for the message (``lens profile``, ``lensfun database file``).
    max_elements : int
        Most elements accepted; the parse stops once there are more.

    Returns
    -------
    xml.etree.ElementTree.Element
        The root element.

    Raises
    ------
    error
        Undecodable, a DTD or entity declaration, not well-formed, absurdly nested, or
        more than ``max_elements`` elements.
    """
    try:
        text = decode_xml(raw)
    except ValueError as exc:
        raise error(one_line(f"{where}: cannot decode the {what} ({exc})")) from None
    # no importer's format has a DTD: refusing one refuses entity expansion and external entities
    if _DTD.search(text):
        raise error(one_line(f"{where}: a DTD or entity declaration is not allowed in a {what}"))
    # its declaration goes: its encoding is no longer the bytes' encoding
    body = _DECLARATION.sub("", text, count=1).encode("utf-8")
    del text
    parser = ET.XMLPullParser(events=("start",))
    seen, root = 0, None

    def count() -> None:
        nonlocal seen, root
        for _event, element in parser.read_events():
            root = element if root is None else root  # the first element to start is the root
            seen += 1
        if seen > max_elements:
            raise error(one_line(f"{where}: more than {max_elements} XML elements is too many for a {what}"))

    try:
        for i in range(0, len(body), _CHUNK):  # fed in chunks, elements counted as they come
            parser.feed(body[i:i + _CHUNK])
            count()
        parser.close()
        count()
    except ET.ParseError as exc:
        raise error(one_line(f"{where}: not an XML {what} ({exc})")) from None
    except RecursionError:
        raise error(one_line(f"{where}: absurdly nested XML")) from None
    if root is None:
        raise error(one_line(f"{where}: not an XML {what} (no element)"))
    return root
