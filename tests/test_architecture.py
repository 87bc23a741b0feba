"""The package's import rules (DESIGN: one direction, no cycles), checked from the source."""

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
    """Module -> the irft_torch modules it imports at module level (function-level imports are lazy
    and allowed: the CLI and optional paths use them)."""
    out = {}
    for path in PKG.rglob("*.py"):
        mod = _module_name(path)
        pkg = mod if path.name == "__init__.py" else mod.rsplit(".", 1)[0]
        deps = set()
        for node in ast.parse(path.read_text()).body:
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


def test_no_import_cycle_between_modules():
    graph = _imports()
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


def test_layers_import_one_way():
    graph = _imports()
    forbidden = {
        "irft_torch.rft": ("irft_torch.gp", "irft_torch.hardware", "irft_torch.design", "irft_torch.plotting"),
        "irft_torch.gp": ("irft_torch.design", "irft_torch.hardware", "irft_torch.plotting", "irft_torch.cli"),
        "irft_torch.hardware": ("irft_torch.gp", "irft_torch.design", "irft_torch.plotting"),
        "irft_torch.design": ("irft_torch.hardware", "irft_torch.plotting"),
    }
    bad = [(m, d) for m, deps in graph.items() for layer, banned in forbidden.items() if m.startswith(layer)
           for d in deps if d.startswith(banned)]
    assert not bad, bad
    # the 0.1 cycle: kernels and operators imported each other
    assert "irft_torch.gp.kernels" not in graph["irft_torch.gp.operators"]


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
