"""Build the API reference from the docstrings with pdoc (``make docs``): ``site/`` by default.

    python docs/build_api.py [OUT]

Every module of the ``diffgcl`` package gets a page (the packages' ``__all__`` lists would hide
their submodules from pdoc's own walk, so the modules are named explicitly); docstrings are read
as reStructuredText, whose roles (``:func:`x```, ``:class:`~x```) pdoc turns into links.

Warnings are errors. pdoc warns about what it cannot import, parse or render; a cross-reference
it cannot resolve it leaves as plain text without a word, so this script also resolves every
role of every docstring itself and fails, naming the module and the reference, on one that names
nothing (a renamed function, a reference broken across two lines).
"""

from __future__ import annotations

import ast
import importlib
import pkgutil
import re
import sys
import warnings
from pathlib import Path

import pdoc
import pdoc.extract
import pdoc.render

PACKAGE = "diffgcl"
ROLE = re.compile(r":(?:func|class|mod|meth|attr|data|obj|exc|const):`~?([^`<>]+?)`")


def module_names() -> list[str]:
    """The package and every module below it, but the ``__main__`` entry points."""
    package = importlib.import_module(PACKAGE)
    found = pkgutil.walk_packages(package.__path__, f"{PACKAGE}.")
    return [PACKAGE] + sorted(m.name for m in found if not m.name.endswith("__main__"))


def resolves(name: str) -> bool:
    """Whether a dotted ``name`` is an importable module or an attribute of one (a dataclass's or
    NamedTuple's field counts, with or without a default)."""
    parts = name.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ImportError:
            continue
        for part in parts[i:]:
            fields = {*getattr(obj, "__dataclass_fields__", ()), *getattr(obj, "_fields", ())}
            if isinstance(obj, type):
                fields |= set(getattr(obj, "__annotations__", {}))
            if hasattr(obj, part):
                obj = getattr(obj, part)
            elif part in fields:
                obj = None
            else:
                break
        else:
            return True
    return False


def broken_references(modules: list[str]) -> list[str]:
    """``module:line: role target`` for every docstring reference that resolves neither as
    written, nor in its module, nor in its class."""
    out = []
    for name in modules:
        module = importlib.import_module(name)
        tree = ast.parse(Path(module.__file__).read_text())
        stack = [(tree, None)]
        while stack:
            node, cls = stack.pop()
            kinds = (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)
            doc = ast.get_docstring(node, clean=False) if isinstance(node, kinds) else None
            for target in ROLE.findall(doc or ""):
                target = target.strip().removesuffix("()")
                candidates = [target, f"{name}.{target}"]
                if cls is not None:
                    candidates.append(f"{name}.{cls}.{target}")
                if not any(resolves(c) for c in candidates):
                    line = getattr(node, "lineno", 1)
                    out.append(f"{name}:{line}: unresolved reference {target!r}")
            for child in ast.iter_child_nodes(node):
                stack.append((child, child.name if isinstance(child, ast.ClassDef) else cls))
    return out


def module_specs(modules: list[str]) -> list[str]:
    """The fewest module names whose walk covers ``modules``: pdoc walks a package's submodules
    itself, except where the package's ``__all__`` leaves them out (the root, ``diffgcl.usv``,
    ``diffgcl.data.synth``), and warns about a module named twice."""
    specs: list[str] = []
    covered: set[str] = set()
    for name in modules:
        if name not in covered:
            specs.append(name)
            covered.update(pdoc.extract.walk_specs([name]))
    return specs


def attribute_namedtuple_constructors(modules: list[str]) -> None:
    """Give each NamedTuple's generated ``__new__`` the module of its class. Python puts it in a
    module of its own (``namedtuple_<Name>``), where pdoc cannot evaluate the class's string
    annotations (``from __future__ import annotations``) and would show them unresolved."""
    for name in modules:
        for obj in vars(importlib.import_module(name)).values():
            if isinstance(obj, type) and issubclass(obj, tuple) and hasattr(obj, "_fields"):
                if obj.__module__ == name and "__new__" in vars(obj):
                    obj.__new__.__module__ = name


# optax.OptState is chex's recursive ArrayTree alias, which typing cannot evaluate outside chex;
# pdoc then shows the annotation as written, which is what it is.
KNOWN_PDOC_WARNINGS = (re.compile(r"Error parsing type annotation optax\.OptState .*ArrayTree"),)


def main(argv: list[str]) -> int:
    out = Path(argv[0] if argv else "site")
    modules = module_names()
    for name in modules:  # import first: a library's own import-time warnings are not pdoc's
        importlib.import_module(name)
    problems = broken_references(modules)
    attribute_namedtuple_constructors(modules)
    pdoc.render.configure(docformat="restructuredtext", show_source=True)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        pdoc.pdoc(*module_specs(modules), output_directory=out)
    problems += [
        f"pdoc: {w.category.__name__}: {w.message}"
        for w in caught
        if not any(known.search(str(w.message)) for known in KNOWN_PDOC_WARNINGS)
    ]
    for problem in problems:
        print(problem, file=sys.stderr)
    if problems:
        print(f"docs: {len(problems)} problem(s), listed above", file=sys.stderr)
        return 1
    print(f"docs: {len(modules)} modules documented in {out}/")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
