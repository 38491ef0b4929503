"""The stamp of a generated file: its content hash and the spec it was generated for.

Every file tvopt-codegen writes carries, in its first lines, the SHA-256 of its own text
and the spec's name. The writer reads them to tell a pristine generated file (it may be
replaced) from one a person edited or another spec's (it is kept); the renderer puts
them in. Neither stage imports the other for it.
"""

from __future__ import annotations

import hashlib
import re

#: Placeholder for the content hash while the hash is computed.
HASH_PLACEHOLDER = "@@CONTENT_SHA256@@"
_HASH_LINE = re.compile(r"content sha256: ([0-9a-f]{64}|" + HASH_PLACEHOLDER + ")")
#: The stamp's line naming the spec a file was generated for (the writer refuses to
#: replace one spec's file with another's).
_SPEC_LINE = re.compile(r"^\W{1,3}spec name: ([A-Za-z][A-Za-z0-9_]*)$", re.MULTILINE)
#: The stamp stands in a file's first lines.
_STAMP_LENGTH = 2000


def stamp_hash(text: str) -> str:
    """SHA-256 of a generated file's text with its content hash replaced by the placeholder."""
    normalized = _HASH_LINE.sub(f"content sha256: {HASH_PLACEHOLDER}", text, count=1)
    return hashlib.sha256(normalized.encode("utf-8")).hexdigest()


def stamped_hash(text: str) -> str | None:
    """The content hash a generated file claims, or ``None`` if it carries no stamp."""
    match = _HASH_LINE.search(text)
    if match is None or match.group(1) == HASH_PLACEHOLDER:
        return None
    return match.group(1)


def stamped_spec(text: str) -> str | None:
    """The spec name a generated file's stamp names, or ``None`` if it names none."""
    match = _SPEC_LINE.search(text, 0, _STAMP_LENGTH)
    return None if match is None else match.group(1)


def is_pristine(text: str) -> bool:
    """Whether ``text`` is a generated file nobody has edited since generation."""
    claimed = stamped_hash(text)
    return claimed is not None and claimed == stamp_hash(text)
