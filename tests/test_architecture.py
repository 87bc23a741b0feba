"""The package's import rules (docs/architecture.md: floors, one direction, no cycles), checked from the source."""

import ast
import pathlib

PKG = pathlib.Path(__file__).resolve().parents[1] / "irft_torch"


def _module_name(path: pathlib.Path) -> str:
    rel = path.relative_to(PKG.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _imports() -> dict[str, set[str]]:
    """Module -> the irft_torch modules it imports: every import statement, at module level or inside a
    function (a lazy import is still a dependency), relative ones resolved."""
    out = {}
    for path in PKG.rglob("*.py"):
        mod = _module_name(path)
        pkg = mod if path.name == "__init__.py" else mod.rsplit(".", 1)[0]
        deps = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom):
                if node.level:
                    base = pkg.split(".")
                    base = base[: len(base) - (node.level - 1)]
                    target = ".".join(base + ([node.module] if node.module else []))
                else:
                    target = node.module or ""
                names = [target] + [f"{target}.{a.name}" for a in node.names]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            else:
                continue
            deps |= {n for n in names if n.startswith("irft_torch")}
        out[mod] = deps
    mods = set(out)
    # keep only names that are modules (drop imported functions/classes)
    return {m: {d for d in deps if d in mods and d != m} for m, deps in out.items()}


# The floors, lowest first (docs/architecture.md): a module imports only from floors below its own and
# from its own package; gp and hardware share a floor and never import each other.
FLOORS = {
    "irft_torch._deprecated": 0, "irft_torch._files": 0, "irft_torch._version": 0,
    "irft_torch.rft": 0,
    "irft_torch.metrics": 1,
    "irft_torch.data": 2, "irft_torch.plotting": 2,
    "irft_torch.gp": 3, "irft_torch.hardware": 3,
    "irft_torch.design": 4,
    "irft_torch.studies": 5,
    "irft_torch.cli": 6,
    # the old import paths (deprecated aliases), above everything they forward to
    "irft_torch.dem_data": 7, "irft_torch.wheel_data": 7, "irft_torch.reproduce": 7, "irft_torch.study_report": 7,
    "irft_torch.workers": 7,
}


def _room(mod: str) -> str:
    """The package (or top-level module) ``mod`` belongs to: irft_torch.gp.backends.pairs -> irft_torch.gp."""
    return ".".join(mod.split(".")[:2])


def test_no_import_cycle_between_modules():
    graph = _imports()
    assert "irft_torch.gp.cross_validation" in graph["irft_torch.gp.model"]  # function-level imports are read
    # a package's __init__ importing its own submodules is not a cycle of concern: drop parent edges
    graph = {m: {d for d in deps if not m.startswith(d + ".")} for m, deps in graph.items()}
    state: dict[str, int] = {}

    def visit(m, stack):
        state[m] = 1
        for d in graph.get(m, ()):
            if state.get(d) == 1:
                raise AssertionError("import cycle: " + " -> ".join(stack[stack.index(d):] + [d]))
            if d not in state:
                visit(d, stack + [d])
        state[m] = 2

    for m in graph:
        if m not in state:
            visit(m, [m])


def test_every_module_has_a_floor_and_imports_only_below_it():
    graph = _imports()
    rooms = {_room(m) for m in graph if m != "irft_torch"}
    assert rooms <= set(FLOORS), f"modules without a floor: {sorted(rooms - set(FLOORS))}"
    bad = []
    for m, deps in graph.items():
        if m == "irft_torch":  # the package's lazy front (PEP 562) reaches every floor
            continue
        for d in deps:
            if d == "irft_torch" or _room(d) == _room(m):
                continue
            if FLOORS[_room(d)] >= FLOORS[_room(m)]:
                bad.append(f"{m} (floor {FLOORS[_room(m)]}) imports {d} (floor {FLOORS[_room(d)]})")
    assert not bad, "\n".join(bad)


def test_only_the_studies_and_the_command_import_plotting():
    graph = _imports()
    users = {_room(m) for m, deps in graph.items() for d in deps if d == "irft_torch.plotting"}
    assert users <= {"irft_torch.studies", "irft_torch.cli"}, users
    # the 0.1 cycle: kernels and operators imported each other
    assert "irft_torch.gp.kernels.angle" not in graph["irft_torch.gp.kernels.operators"]


def test_no_module_over_600_lines_without_saying_why():
    """One concept per module: a module over 600 lines ends with a closing note, a comment line
    ``# One concept: ...``, saying why it is one."""
    long = []
    for path in PKG.rglob("*.py"):
        lines = path.read_text().rstrip().splitlines()
        if len(lines) > 600 and not lines[-1].startswith("# One concept:"):
            long.append(f"{path.relative_to(PKG.parent)}: {len(lines)} lines")
    assert not long, long


def test_package_and_command_parsing_do_not_import_torch():
    """``import irft_torch`` and parsing an ``irft`` command stay light (the subpackages load on first
    use), so ``irft --help`` answers at once and ``irft reproduce`` starts its workers' imports first."""
    import subprocess
    import sys

    code = ("import sys, irft_torch, irft_torch.cli as cli\n"
            "cli.build_parser().parse_args(['reproduce', '--quick'])\n"
            "assert 'torch' not in sys.modules, 'torch imported'\n"
            "assert irft_torch.InverseRFT.__name__ == 'InverseRFT' and 'torch' in sys.modules\n"
            "from irft_torch import Posterior, rft\n"
            "assert rft.FourierStressMap.generic() is not None\n"
            "try:\n    irft_torch.no_such_name\nexcept AttributeError as e:\n    assert 'no_such_name' in str(e)\n"
            "else:\n    raise SystemExit('no AttributeError')\n")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert p.returncode == 0, p.stderr[-2000:]
