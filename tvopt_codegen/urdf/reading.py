"""A URDF file read at the door: its bytes, its text, its strict XML tree, its robot.

The file is opened without blocking and must be a regular file of at most 1 MB; its text
is decoded (byte-order mark, UTF-16/32, the declared encoding) before a DOCTYPE is looked
for, the XML parser reads exactly the text that was checked, and every element is checked
(:func:`~tvopt_codegen.urdf.elements._check_elements`) before ``yourdfpy`` reads it.
"""

from __future__ import annotations

import codecs
import io
import os
import re
import stat
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from tvopt_codegen.spec.files import MAX_SPEC_BYTES
from tvopt_codegen.spec.toml_shape import MAX_NESTING
from tvopt_codegen.urdf.elements import _check_elements, _fail

#: Most XML elements a URDF file may hold (the spec's own limits are on bytes and depth).
MAX_ELEMENTS = 200_000


def _read(path: Path) -> bytes:
    """The file's bytes, once it is known to be a regular file of bounded size.

    Opened without blocking and checked on the open descriptor: a FIFO would wait for a
    writer forever and ``/dev/zero`` never ends, and a check by name before opening
    could be raced by a rename.
    """
    source = str(path)
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_NOCTTY", 0)
    try:
        fd = os.open(path, flags)
    except OSError as exc:
        raise _fail(source, "(file)", f"cannot read: {exc.strerror or exc}") from None
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise _fail(source, "(file)", f"is {_file_kind(info.st_mode)}, not a regular file")
        if info.st_size > MAX_SPEC_BYTES:
            raise _fail(
                source, "(file)", f"{info.st_size} bytes, larger than {MAX_SPEC_BYTES} bytes"
            )
        with os.fdopen(fd, "rb", closefd=False) as handle:
            data = handle.read(MAX_SPEC_BYTES + 1)
    except OSError as exc:
        raise _fail(source, "(file)", f"cannot read: {exc.strerror or exc}") from None
    finally:
        os.close(fd)
    if len(data) > MAX_SPEC_BYTES:  # it grew while it was read
        raise _fail(source, "(file)", f"larger than {MAX_SPEC_BYTES} bytes")
    return data


def _file_kind(mode: int) -> str:
    """What a file that is not a regular one is, in words."""
    kinds = (
        (stat.S_ISDIR, "a directory"),
        (stat.S_ISFIFO, "a FIFO (named pipe)"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
        (stat.S_ISSOCK, "a socket"),
    )
    return next((word for test, word in kinds if test(mode)), "a special file")


#: Byte-order marks, longest first (UTF-32 LE's begins with UTF-16 LE's).
_BOMS = (
    (codecs.BOM_UTF32_BE, "utf-32-be"),
    (codecs.BOM_UTF32_LE, "utf-32-le"),
    (codecs.BOM_UTF8, "utf-8"),
    (codecs.BOM_UTF16_BE, "utf-16-be"),
    (codecs.BOM_UTF16_LE, "utf-16-le"),
)

#: How ``<?`` or ``<`` begins a document without a mark (XML 1.0, appendix F).
_STARTS = (
    (b"\x00\x00\x00<", "utf-32-be"),
    (b"<\x00\x00\x00", "utf-32-le"),
    (b"\x00<\x00?", "utf-16-be"),
    (b"<\x00?\x00", "utf-16-le"),
)

_DECLARATION = re.compile(r"""\A\s*<\?xml\b[^>]*?\?>""")
_DECLARED = re.compile(r"""encoding\s*=\s*["']([A-Za-z0-9._-]+)["']""")


def _decode(data: bytes, source: str) -> str:
    """The document as text, in the encoding its mark, first bytes or declaration give.

    Everything later (the DOCTYPE refusal, the XML parser) reads this text, so that no
    encoding can hide a declaration from the check that the parser then sees.
    """
    encoding = next((name for mark, name in _BOMS if data.startswith(mark)), None)
    body = data
    if encoding is not None:
        body = data[len(next(mark for mark, name in _BOMS if name == encoding)) :]
    else:
        encoding = next((name for start, name in _STARTS if data.startswith(start)), None)
    if encoding is None:
        # EBCDIC writes "<?xm" as 4C 6F A7 94: its declaration is read in EBCDIC.
        head = data[:200].decode("cp500" if data.startswith(b"\x4c\x6f\xa7\x94") else "latin-1")
        declared = _DECLARATION.match(head)
        named = _DECLARED.search(declared.group(0)) if declared else None
        encoding = named.group(1) if named else "utf-8"
        try:
            codecs.lookup(encoding)
        except LookupError:
            raise _fail(source, "(file)", f"declares an unknown encoding {encoding!r}") from None
    try:
        text = body.decode(encoding)
    except (UnicodeDecodeError, LookupError) as exc:
        reason = getattr(exc, "reason", str(exc))
        raise _fail(source, "(file)", f"is not valid {encoding}: {reason}") from None
    return text.lstrip("\ufeff")


def _load(path: Path) -> tuple[Any, Any]:
    """The file's checked XML tree and the URDF model yourdfpy reads from it."""
    source = str(path)
    text = _decode(_read(path), source)
    if re.search(r"<!\s*(DOCTYPE|ENTITY)", text, re.IGNORECASE):
        # Entities expand (a billion laughs) or reach files (XXE): a robot needs neither.
        raise _fail(source, "(file)", "holds a DOCTYPE or ENTITY declaration, which is refused")
    if text.count("<") > MAX_ELEMENTS:
        raise _fail(source, "(file)", f"more than {MAX_ELEMENTS} XML elements")
    try:
        import yourdfpy  # noqa: PLC0415 - the urdf extra, on use
        from lxml import etree  # noqa: PLC0415 - yourdfpy's own XML library
    except ImportError:
        raise _fail(
            source, "(file)", "reading URDF needs yourdfpy: pip install 'tvopt-codegen[urdf]'"
        ) from None
    # The parser reads the decoded text, its declaration removed, as UTF-8: the bytes it
    # sees are those just checked, whatever the file's own encoding was.
    checked = _DECLARATION.sub("", text, count=1).encode("utf-8", "surrogatepass")
    # Well-formedness first, strictly: yourdfpy falls back to a recovering parser, which
    # would read a broken file as some other robot.
    parser = etree.XMLParser(
        resolve_entities=False, no_network=True, huge_tree=False, load_dtd=False
    )
    try:
        root = etree.fromstring(checked, parser=parser)
    except (etree.XMLSyntaxError, ValueError) as exc:
        raise _fail(source, "(file)", f"not well-formed XML: {exc}") from None
    tree = root.getroottree()
    if tree.docinfo.doctype or any(isinstance(node, etree._Entity) for node in root.iter()):
        raise _fail(source, "(file)", "holds a DOCTYPE or entity reference, which is refused")
    if root.tag != "robot":
        raise _fail(source, "(file)", f"the root element is <{root.tag}>, not <robot>")
    # The spec's nesting limit: a robot is a few levels deep.
    deepest = max((sum(1 for _ in node.iterancestors()) for node in root.iter()), default=0)
    if deepest > MAX_NESTING:
        raise _fail(source, "(file)", f"elements nest {deepest} deep (at most {MAX_NESTING})")
    _check_elements(root, source)
    try:
        # No meshes are read and no scene graph is built: the dynamics need neither. The
        # values are checked above; what yourdfpy or trimesh would warn of is not news.
        with warnings.catch_warnings(), np.errstate(all="ignore"):
            warnings.simplefilter("ignore")
            model = yourdfpy.URDF.load(
                io.BytesIO(checked),
                build_scene_graph=False,
                build_collision_scene_graph=False,
                load_meshes=False,
                load_collision_meshes=False,
            )
    except (ValueError, TypeError, AttributeError, KeyError, IndexError) as exc:
        raise _fail(source, "(file)", f"not a URDF robot: {exc}") from None
    return root, model.robot
