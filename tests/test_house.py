"""Rules of the package's shape that a reader relies on, checked on its source."""
import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "psdr_cli"

#: The most positional parameters a function takes (``self``/``cls`` not counted); more travel
#: as a record or as keyword-only arguments.
MAX_POSITIONAL = 7


def functions(path: Path):
    """(name, line, positional parameter names) of every function defined in ``path``."""
    tree = ast.parse(path.read_text())
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            names = [a.arg for a in node.args.posonlyargs + node.args.args]
            if names and names[0] in ("self", "cls"):
                names = names[1:]
            yield node.name, node.lineno, names


def test_no_function_takes_more_than_seven_positional_parameters():
    """Long positional lists are where arguments get swapped; the typer commands of ``cli.py``
    (one parameter per command-line option) are exempt."""
    long = [f"{path.relative_to(PACKAGE.parent)}:{line} {name} ({len(names)})"
            for path in sorted(PACKAGE.rglob("*.py")) if path.name != "cli.py"
            for name, line, names in functions(path) if len(names) > MAX_POSITIONAL]
    assert not long, "more than 7 positional parameters:\n" + "\n".join(long)


def term_names_in_code(path: Path, names) -> list:
    """Lines of ``path`` whose code (docstrings aside) holds one of ``names`` as a string literal."""
    tree = ast.parse(path.read_text())
    docstrings = {id(node.body[0].value) for node in ast.walk(tree)
                  if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef))
                  and node.body and isinstance(node.body[0], ast.Expr) and isinstance(node.body[0].value, ast.Constant)}
    return [node.lineno for node in ast.walk(tree)
            if isinstance(node, ast.Constant) and node.value in names and id(node) not in docstrings]


def test_only_the_estimators_and_the_config_name_a_term():
    """A term is found through its interface (the registry, its ``Term``'s fields): a module
    outside ``estimators/`` and ``config/`` that names one by its string would miss a term added
    the README's way."""
    from psdr_cli.config.vocabularies import TERMS
    named = [f"{path.relative_to(PACKAGE.parent)}:{line}" for path in sorted(PACKAGE.rglob("*.py"))
             if path.parent.name not in ("estimators", "config")
             for line in term_names_in_code(path, set(TERMS))]
    assert not named, "term names outside estimators/ and config/:\n" + "\n".join(named)


def writes_through(path: Path, name: str) -> list:
    """Lines of ``path`` that assign through a variable or attribute called ``name``: a target
    such as ``name.x = …``, ``name.params[k] = …`` or ``now.name.scene.y += …`` (assigning
    ``now.name`` itself is not writing through it)."""
    def through(node) -> bool:
        node = node.value if isinstance(node, (ast.Attribute, ast.Subscript)) else None
        while node is not None:
            if (isinstance(node, ast.Name) and node.id == name) or (isinstance(node, ast.Attribute) and node.attr == name):
                return True
            node = node.value if isinstance(node, (ast.Attribute, ast.Subscript)) else None
        return False
    tree = ast.parse(path.read_text())
    lines = []
    for node in ast.walk(tree):
        targets = node.targets if isinstance(node, ast.Assign) else \
            [node.target] if isinstance(node, (ast.AugAssign, ast.AnnAssign)) else []
        flat = [t for target in targets for t in (target.elts if isinstance(target, ast.Tuple) else [target])]
        lines += [node.lineno for t in flat if through(t)]
    return lines


def test_only_the_problem_and_its_unknowns_write_the_problem():
    """The optimisation's state is written by ``optimisation/problem.py`` and the unknowns
    (``optimisation/unknowns/``) only: every other module asks the problem (``apply``,
    ``invalidate``, ``write_saved``, ``step``, ...) rather than assigning through a ``problem``.
    (A problem bound to another name escapes this check; the convention is the name ``problem``.)"""
    allowed = {PACKAGE / "optimisation" / "problem.py"}
    found = [f"{path.relative_to(PACKAGE.parent)}:{line}" for path in sorted(PACKAGE.rglob("*.py"))
             if path not in allowed and path.parent.name != "unknowns"
             for line in writes_through(path, "problem")]
    assert not found, "assignments through a problem outside problem.py and unknowns/:\n" + "\n".join(found)
