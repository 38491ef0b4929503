"""Where specs come from: files (bounded reads), bundled examples and plain mappings."""

from __future__ import annotations

import hashlib
import json
import re
import tomllib
from collections.abc import Mapping
from importlib import resources
from pathlib import Path
from typing import Any

from tvopt_codegen.errors import SpecError
from tvopt_codegen.spec.reader import _Reader
from tvopt_codegen.spec.toml_shape import ShapeError, check_shape
from tvopt_codegen.spec.types import Spec

#: Largest spec file accepted, in bytes.
MAX_SPEC_BYTES = 1_000_000


#: Appended to a bundled example's file name where messages name the spec.
BUNDLED_SUFFIX = " (bundled example)"


#: A sentence's end: a full stop before a space or the end, but not after an abbreviation
#: the examples use ("Sec. V-A", "Fig. 3").
_SENTENCE_END = re.compile(r"(?<!\bSec)(?<!\bFig)(?<!\bEq)(?<!\be\.g)(?<!\bi\.e)\.(?=\s|$)")


def first_sentence(text: str) -> str:
    """The first sentence of a description, its lines joined (a summary never ends mid-way)."""
    joined = " ".join(text.split())
    match = _SENTENCE_END.search(joined)
    return joined if match is None else joined[: match.end()]


def bundled_examples() -> dict[str, str]:
    """Return the bundled example specs: name -> the first sentence of the description."""
    found: dict[str, str] = {}
    for entry in sorted(resources.files("tvopt_codegen.examples").iterdir(), key=lambda e: e.name):
        if entry.name.endswith(".toml"):
            data = tomllib.loads(entry.read_text(encoding="utf-8"))
            found[entry.name[: -len(".toml")]] = first_sentence(str(data.get("description", "")))
    return found


def read_spec_bytes(spec: str | Path) -> tuple[str, bytes]:
    """Find a spec by path or bundled-example name and return (display name, bytes).

    Parameters
    ----------
    spec : str or pathlib.Path
        A path to a TOML file, or the name of a bundled example.

    Returns
    -------
    tuple of (str, bytes)
        The name to use in messages and the raw file content.

    Raises
    ------
    SpecError
        When neither a readable file nor a bundled example of that name exists.
    """
    path = Path(spec)
    if path.suffix.lower() in {".yaml", ".yml"}:
        raise SpecError(
            str(spec),
            "(file)",
            "YAML specs are not supported (YAML 1.1 reads no as "
            "false and 1e-3 as a string); write the spec in TOML",
        )
    if path.is_file():
        size = path.stat().st_size
        if size > MAX_SPEC_BYTES:
            raise SpecError(
                str(spec), "(file)", f"file is {size} bytes; the limit is {MAX_SPEC_BYTES}"
            )
        try:
            return str(spec), path.read_bytes()
        except OSError as exc:
            raise SpecError(str(spec), "(file)", f"cannot read: {exc.strerror}") from None
    if path.exists():
        raise SpecError(str(spec), "(file)", "not a regular file")
    name = str(spec)
    examples = resources.files("tvopt_codegen.examples")
    candidate = examples / f"{name}.toml"
    if name.isidentifier() and candidate.is_file():
        return f"{name}.toml{BUNDLED_SUFFIX}", candidate.read_bytes()
    known = ", ".join(bundled_examples())
    raise SpecError(
        str(spec), "(file)", f"no such file, and no bundled example of that name ({known})"
    )


def load_spec(spec: str | Path) -> Spec:
    """Read, validate and parse a spec file.

    Parameters
    ----------
    spec : str or pathlib.Path
        A path to a TOML spec, or the name of a bundled example
        (see :func:`bundled_examples`).

    Returns
    -------
    Spec
        The validated spec.

    Raises
    ------
    SpecError
        For any problem, naming the file, the field and the problem.
    """
    source, raw = read_spec_bytes(spec)
    return parse_spec(source, raw)


def spec_from_dict(data: Mapping[str, Any], source: str = "<python>") -> Spec:
    """A spec from a mapping laid out as the TOML file would be: no file needed.

    Parameters
    ----------
    data : mapping
        Tables as dicts, lists as lists, expressions as strings, numbers as numbers.
    source : str
        The name messages give it.

    Returns
    -------
    Spec
        The validated spec; its SHA-256 is that of the mapping as canonical JSON.

    Raises
    ------
    SpecError
        For any problem, naming the field and the problem.
    """
    if not isinstance(data, Mapping):
        raise SpecError(source, "(spec)", f"expected a mapping, got {type(data).__name__}")
    try:
        canonical = json.dumps(data, sort_keys=True, allow_nan=False).encode("utf-8")
    except (TypeError, ValueError) as exc:
        raise SpecError(source, "(spec)", f"not a plain mapping of tables: {exc}") from None
    return _Reader(source).read(data, hashlib.sha256(canonical).hexdigest())


def parse_spec(source: str, raw: bytes) -> Spec:
    """Validate and parse spec bytes; ``source`` names them in messages.

    Parameters
    ----------
    source : str
        Display name of the spec, used in every error message.
    raw : bytes
        The file content (UTF-8 TOML).

    Returns
    -------
    Spec
        The validated spec.
    """
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise SpecError(source, "(file)", f"not UTF-8 text (byte {exc.start})") from None
    if "\x00" in text:
        raise SpecError(source, "(file)", "binary file (contains NUL bytes)")
    try:
        check_shape(text)
    except ShapeError as exc:
        raise SpecError(source, "(file)", str(exc)) from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise SpecError(source, "(file)", f"TOML syntax error: {exc}") from None
    return _Reader(source).read(data, hashlib.sha256(raw).hexdigest())
