"""The contract every code-generation backend fulfils."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # the engine loads in a second; the registry is read by --help too
    from tvopt_codegen.lowering.printers import ExpressionPrinter, JointPrinter


@dataclass(frozen=True)
class Backend:
    """A target language.

    Attributes
    ----------
    name : str
        The name users pass to ``--backend``.
    description : str
        One line for ``--help``.
    printer : callable
        Builds the expression printer (an
        :class:`~tvopt_codegen.lowering.printers.ExpressionPrinter`); called when
        rendering, so that registering a backend imports no printer.
    templates : tuple of (str, str)
        Template path (under ``templates/``) and output file name pattern, where
        ``{name}`` is the spec's module name.
    module : str
        The file name pattern of the Python module users (and ``simulate``) import;
        distinct per backend, so that backends can share an output folder.
    variants : tuple of (str, callable)
        More printings of the same kernels, each with its own printer, given to the
        templates as ``kernels_<key>`` (the Python backend's one-point kernels).
    joint : callable or None
        Builds a printer that prints the main printing and some variants at once: its
        ``texts()`` maps ``""`` and variant keys to functions from its text to theirs.
        Rendering then prints each kernel once; variants it does not cover are printed
        by their own printers. None: every printing is printed on its own.
    context : callable or None
        ``context(kernels)`` returns the backend's own template variables (added to the
        shared ones: ``d``, ``spec``, ``kernels``, ``prefix``, ...); ``kernels`` is the
        :class:`~tvopt_codegen.lowering.kernel.KernelSet` being rendered. (Typed ``Any`` here: the
        spec reader consults this registry for reserved words, so the record must not
        depend on the stages after it.)
    filters : callable or None
        ``filters()`` returns the backend's own jinja filters by name (called when the
        template environment is built, so that registering a backend imports none).
    load : callable or None
        ``load(files, module_file, name)`` imports the module users import from the
        rendered ``files`` (``simulate`` runs it); None: the files are written to a
        private folder and ``module_file`` is imported from there.
    template_root : pathlib.Path or None
        The folder its template paths are relative to; None for the shipped
        ``templates/`` (a backend from another package brings its own).
    reserved : frozenset of str
        Words the target language reserves: no spec name may be one of them.
    reserved_as : tuple of (str, frozenset of str)
        Reserved words grouped by what they are (``"a C keyword"``), for the message that
        refuses such a name; words in none of the groups are "a reserved word of the
        <name> backend".
    """

    name: str
    description: str
    printer: Callable[[], ExpressionPrinter]
    templates: tuple[tuple[str, str], ...]
    module: str
    variants: tuple[tuple[str, Callable[[], ExpressionPrinter]], ...] = ()
    joint: Callable[[], JointPrinter] | None = None
    context: Callable[[Any], dict[str, Any]] | None = None
    filters: Callable[[], dict[str, Callable[..., Any]]] | None = None
    load: Callable[[dict[str, str], str, str], ModuleType] | None = None
    template_root: Path | None = None
    reserved: frozenset[str] = frozenset()
    reserved_as: tuple[tuple[str, frozenset[str]], ...] = ()
