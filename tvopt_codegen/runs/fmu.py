"""The stateful controller as a co-simulation FMU (FMI 2.0 or 3.0), built from the C.

An FMU is a zip archive: ``modelDescription.xml`` (inputs the plant states, outputs the
plant input, the spec's parameters tunable, the controller states as locals, the model
structure), the C sources (the C backend's ``<name>.c`` and ``<name>.h`` and the FMI
glue, so that an importer can build it for its platform) and a shared library for this
platform, compiled here. No Python runs inside it. Each ``doStep(tc, h)`` steps the
controller at ``tc`` with the inputs set for ``tc``; the outputs are the input it
returns, held over the step.

The FMI headers are the importer's, by the standard's rule: they are not in the
sources. Building the binary here takes them from FMPy (the ``fmu`` extra) or from the
folder ``TVOPT_CODEGEN_FMI_HEADERS`` names.
"""

from __future__ import annotations

import hashlib
import importlib.util
import io
import os
import platform
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

from tvopt_codegen.derivation import calculus
from tvopt_codegen.emit.caches import build_key, kept_bytes
from tvopt_codegen.errors import BuildError, MissingExtraError
from tvopt_codegen.lowering.ir import KernelSet
from tvopt_codegen.renderer.rendering import render, render_template, template_context
from tvopt_codegen.toolchain import CFLAGS, compiler

#: The FMI versions an FMU can be exported for.
FMI_VERSIONS = (2, 3)
#: Every archive member's time stamp: the FMU's bytes depend on its content alone.
_ZIP_DATE = (1980, 1, 1, 0, 0, 0)


def guid(kernels: KernelSet, fmi: int) -> str:
    """The FMU's GUID (FMI 2) or instantiation token (FMI 3), from the spec's content."""
    spec = kernels.derivation.spec
    digest = hashlib.sha256(f"{spec.sha256}:{spec.name}:fmi{fmi}".encode()).hexdigest()
    return f"{{{digest[:8]}-{digest[8:12]}-{digest[12:16]}-{digest[16:20]}-{digest[20:32]}}}"


def platform_folder(fmi: int) -> str:
    """The ``binaries/`` folder of this platform, in the naming of the FMI version.

    Raises
    ------
    BuildError
        On a platform the FMI standard has no name for here.
    """
    machine = platform.machine().lower()
    arch = {"x86_64": "x86_64", "amd64": "x86_64", "aarch64": "aarch64", "arm64": "aarch64"}
    system = {"linux": "linux", "darwin": "darwin", "win32": "windows"}.get(sys.platform)
    if machine not in arch or system is None:
        raise BuildError(f"no FMI platform name for {sys.platform} on {machine}")
    if fmi == 3:
        return f"{arch[machine]}-{system}"
    if arch[machine] != "x86_64":
        raise BuildError(f"FMI 2 names no platform for {sys.platform} on {machine}: use --fmi 3")
    return {"linux": "linux64", "darwin": "darwin64", "windows": "win64"}[system]


def fmi_headers(fmi: int) -> Path:
    """The folder with ``fmi<fmi>Functions.h``: TVOPT_CODEGEN_FMI_HEADERS, else FMPy's.

    Raises
    ------
    MissingExtraError
        When neither has them.
    """
    wanted = f"fmi{fmi}Functions.h"
    named = os.environ.get("TVOPT_CODEGEN_FMI_HEADERS")
    if named:
        if (Path(named) / wanted).is_file():
            return Path(named)
        raise MissingExtraError(f"TVOPT_CODEGEN_FMI_HEADERS={named!r} has no {wanted}")
    found = importlib.util.find_spec("fmpy")
    if found is not None and found.origin is not None:
        folder = Path(found.origin).parent / "c-code"
        if (folder / wanted).is_file():
            return folder
    raise MissingExtraError(
        "building an FMU needs the FMI headers: pip install 'tvopt-codegen[fmu]' "
        "(or set TVOPT_CODEGEN_FMI_HEADERS to a folder holding them)"
    )


def fmu_sources(kernels: KernelSet, fmi: int) -> dict[str, str]:
    """The FMU's text members: ``modelDescription.xml`` and ``sources/`` (pure).

    Parameters
    ----------
    kernels : KernelSet
        The lowered controller.
    fmi : int
        2 or 3.

    Returns
    -------
    dict of str to str
        Archive member name to text.
    """
    if fmi not in FMI_VERSIONS:
        raise ValueError(f"fmi must be one of {FMI_VERSIONS}, got {fmi!r}")
    name = kernels.derivation.spec.name
    c_files = render(kernels, "c")
    context = template_context(kernels, "c") | {
        "guid": guid(kernels, fmi),
        "reference_start": reference_start(kernels),
    }
    return {
        "modelDescription.xml": render_template(f"fmu/modelDescription{fmi}.xml.jinja", context),
        f"sources/{name}.h": c_files[f"{name}.h"],
        f"sources/{name}.c": c_files[f"{name}.c"],
        f"sources/{name}_fmi{fmi}.c": render_template(f"fmu/fmi{fmi}.c.jinja", context),
    }


def reference_start(kernels: KernelSet) -> tuple[float, ...]:
    """The reference jets at t = 0 from the nominal closed forms (0 without one), flat."""
    d = kernels.derivation
    model = d.model
    defaults = dict(zip(model.params, model.defaults, strict=True))
    return tuple(
        float(term.xreplace(defaults).xreplace({model.t: 0}))
        for row in calculus.nominal_jets(model, d.jet.reference_order)
        for term in row
    )


def build_fmu(kernels: KernelSet, fmi: int = 2) -> bytes:
    """The FMU archive: sources, model description and this platform's binary.

    Parameters
    ----------
    kernels : KernelSet
        The lowered controller.
    fmi : int, optional
        2 (default) or 3.

    Returns
    -------
    bytes
        The ``.fmu`` file's content (deterministic for given sources and compiler).

    Raises
    ------
    MissingExtraError
        Without the FMI headers.
    BuildError
        Without a C compiler, or when it fails.
    """
    name = kernels.derivation.spec.name
    members = fmu_sources(kernels, fmi)
    headers = fmi_headers(fmi)
    folder = platform_folder(fmi)
    suffix = {"darwin": ".dylib", "win32": ".dll"}.get(sys.platform, ".so")
    binary = _library(name, members, fmi, headers, suffix)
    archive = io.BytesIO()
    with zipfile.ZipFile(archive, "w", zipfile.ZIP_DEFLATED) as fmu:
        entries = {member: text.encode("utf-8") for member, text in members.items()}
        entries[f"binaries/{folder}/{name}{suffix}"] = binary
        for member in sorted(entries):
            info = zipfile.ZipInfo(member, date_time=_ZIP_DATE)
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            fmu.writestr(info, entries[member])
    return archive.getvalue()


def _library(name: str, members: dict[str, str], fmi: int, headers: Path, suffix: str) -> bytes:
    """The FMU's shared library for this platform: compiled once per content, then kept.

    The library is a function of the compiler, its version and flags, the sources, the
    FMI headers they include and the platform's suffix (the archive is deterministic for
    given sources and compiler), so an export again of the same controller, or another
    process's (a test run's workers), reads it from the cache folder of the compiled
    libraries instead of running the compiler.
    """
    parts = [f"fmi{fmi}{suffix}"]
    parts += [f"{member}\0{text}" for member, text in sorted(members.items())]
    for header in sorted(headers.glob(f"fmi{fmi}*.h")):
        parts.append(f"{header.name}\0{header.read_text(encoding='utf-8', errors='replace')}")
    return kept_bytes(
        f"fmu-{build_key(parts)[:32]}{suffix}",
        lambda: _compile(name, members, fmi, headers, suffix),
    )


def _compile(name: str, members: dict[str, str], fmi: int, headers: Path, suffix: str) -> bytes:
    """The FMU's library linked in a temporary folder from the controller's object; its bytes.

    The controller's object is :func:`_controller_object`'s; the FMI glue is compiled
    here. The same bytes as compiling both sources in one command (gcc and clang compile each
    to an object and link those), so the archive does not depend on which way it was made.
    """
    controller = _controller_object(name, members)
    with tempfile.TemporaryDirectory(prefix="tvopt-fmu-") as tmp:
        root = Path(tmp)
        for member, text in members.items():
            (root / member).parent.mkdir(parents=True, exist_ok=True)
            (root / member).write_text(text, encoding="utf-8")
        obj = root / f"{name}.o"
        obj.write_bytes(controller)
        library = root / f"{name}{suffix}"
        command = [
            compiler(),
            *CFLAGS,
            "-I",
            str(root / "sources"),
            "-I",
            str(headers),
            "-o",
            str(library),
            str(obj),
            str(root / "sources" / f"{name}_fmi{fmi}.c"),
            "-lm",
        ]
        _run_compiler(command)
        return library.read_bytes()


def _controller_object(name: str, members: dict[str, str]) -> bytes:
    """The controller's C compiled for the FMU's library, once per content, then kept.

    A function of the compiler, its version and flags and the controller's ``.c`` and
    ``.h`` alone: the FMI 2 and the FMI 3 FMU of one controller link the same object, and
    only their glue is compiled for each (the controller is most of the compiler's work).
    """
    sources = {f"{name}{ext}": members[f"sources/{name}{ext}"] for ext in (".c", ".h")}
    parts = ["object", *(f"{member}\0{text}" for member, text in sorted(sources.items()))]

    def build() -> bytes:
        with tempfile.TemporaryDirectory(prefix="tvopt-fmu-") as tmp:
            root = Path(tmp)
            for member, text in sources.items():
                (root / member).write_text(text, encoding="utf-8")
            obj = root / f"{name}.o"
            # -shared is the link's: compiling an object, it has nothing to say.
            flags = [flag for flag in CFLAGS if flag != "-shared"]
            _run_compiler([compiler(), *flags, "-c", str(root / f"{name}.c"), "-o", str(obj)])
            return obj.read_bytes()

    return kept_bytes(f"fmu-{build_key(parts)[:32]}.o", build)


def _run_compiler(command: list[str]) -> None:
    """Run the C compiler; its first line of complaint is the error if it fails."""
    done = subprocess.run(command, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        first = (done.stderr.strip().splitlines() or ["(no message)"])[0]
        raise BuildError(f"compiling the FMU's library failed: {first}")
