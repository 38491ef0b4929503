"""Specs from robot models as roboticists write them: SymPy mechanics.

:func:`spec_from_sympy` turns the equations of motion that ``sympy.physics.mechanics``
forms (``KanesMethod``, ``LagrangesMethod``, or a ``System`` after ``form_eoms()``)
into a spec in mass-matrix form (``[system.mechanics]``, docs/spec.md): the
generalized coordinates and their rates become the states, the other dynamic symbols
of the forcing the inputs, and every other free symbol a named parameter that
``--plant-param`` can perturb. :func:`spec_toml` writes that mapping as TOML text.

Both are total: what they return reads back, through the project's own reader, as
the same spec; what the spec language cannot say is refused at the call, with one
:class:`~tvopt_codegen.errors.SpecError` naming the field, and nothing is written.

``M`` is never inverted here or later: the generated code factors it at run time.

The package, by stage: :mod:`.equations` reads the ``M``, the forcing and the names
from SymPy mechanics and splits the forcing as ``F + B u``; :mod:`.language` checks what
the spec language can say; :mod:`.printing` writes expressions as text the reader reads
back; :mod:`.from_sympy` assembles the spec mapping; :mod:`.readback` reads it back;
:mod:`.toml_text` writes it as TOML. Every name the single module ``mechanics.py`` had
is importable from here.
"""

from tvopt_codegen.mechanics.equations import _equations as _equations
from tvopt_codegen.mechanics.equations import _input_order as _input_order
from tvopt_codegen.mechanics.equations import _natural as _natural
from tvopt_codegen.mechanics.equations import _rate_of as _rate_of
from tvopt_codegen.mechanics.equations import _unique as _unique
from tvopt_codegen.mechanics.from_sympy import DEFAULT_POLES as DEFAULT_POLES
from tvopt_codegen.mechanics.from_sympy import _initial_state as _initial_state
from tvopt_codegen.mechanics.from_sympy import _parameter_values as _parameter_values
from tvopt_codegen.mechanics.from_sympy import spec_from_sympy
from tvopt_codegen.mechanics.language import _ALLOWED_CLASSES as _ALLOWED_CLASSES
from tvopt_codegen.mechanics.language import _ALLOWED_TEXT as _ALLOWED_TEXT
from tvopt_codegen.mechanics.language import _RECIPROCALS as _RECIPROCALS
from tvopt_codegen.mechanics.language import MAX_NODES as MAX_NODES
from tvopt_codegen.mechanics.language import SOURCE_SYMPY as SOURCE_SYMPY
from tvopt_codegen.mechanics.language import _check_depth as _check_depth
from tvopt_codegen.mechanics.language import _check_tree as _check_tree
from tvopt_codegen.mechanics.language import _fail as _fail
from tvopt_codegen.mechanics.language import _name as _name
from tvopt_codegen.mechanics.language import _number as _number
from tvopt_codegen.mechanics.language import _refusal as _refusal
from tvopt_codegen.mechanics.language import _sayable as _sayable
from tvopt_codegen.mechanics.language import _symbol_name as _symbol_name
from tvopt_codegen.mechanics.printing import _CHAIN as _CHAIN
from tvopt_codegen.mechanics.printing import _GROUPS as _GROUPS
from tvopt_codegen.mechanics.printing import _PRINTER as _PRINTER
from tvopt_codegen.mechanics.printing import _exact as _exact
from tvopt_codegen.mechanics.printing import _groups as _groups
from tvopt_codegen.mechanics.printing import _power_of_ten as _power_of_ten
from tvopt_codegen.mechanics.printing import _Printer as _Printer
from tvopt_codegen.mechanics.printing import _text as _text
from tvopt_codegen.mechanics.readback import _rational as _rational
from tvopt_codegen.mechanics.readback import _reads_back as _reads_back
from tvopt_codegen.mechanics.readback import _same as _same
from tvopt_codegen.mechanics.toml_text import _BARE_KEY as _BARE_KEY
from tvopt_codegen.mechanics.toml_text import _ESCAPES as _ESCAPES
from tvopt_codegen.mechanics.toml_text import MAX_TOML_DEPTH as MAX_TOML_DEPTH
from tvopt_codegen.mechanics.toml_text import SOURCE_TOML as SOURCE_TOML
from tvopt_codegen.mechanics.toml_text import _key as _key
from tvopt_codegen.mechanics.toml_text import _plain_data as _plain_data
from tvopt_codegen.mechanics.toml_text import _string as _string
from tvopt_codegen.mechanics.toml_text import _toml_fail as _toml_fail
from tvopt_codegen.mechanics.toml_text import _value as _value
from tvopt_codegen.mechanics.toml_text import spec_toml

__all__ = ["spec_from_sympy", "spec_toml"]
