"""The architecture holds: imports flow scenarios → sim_interrogator → models → twin, never back, and the sensing
core imports without the optional packages."""

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: package → packages it must never import
FORBIDDEN = {
    "twin": {"models", "sim_interrogator", "scenarios"},
    "models": {"sim_interrogator", "scenarios"},
    "sim_interrogator": {"scenarios"},
}
OPTIONAL = ("mujoco", "meshcat", "matplotlib", "h5py", "dask", "distributed", "pyarrow", "zmq", "tornado", "umsgpack",
            "mcap", "zstandard", "lz4", "foxglove", "rosbags", "mcap_ros2")


def _imports(path: Path):
    tree = ast.parse(path.read_text(), filename=str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield node.lineno, alias.name
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            yield node.lineno, node.module


def test_no_import_points_back_up_the_layers():
    bad = []
    for package, forbidden in FORBIDDEN.items():
        for path in sorted((ROOT / package).rglob("*.py")):
            for line, name in _imports(path):
                if name.split(".")[0] in forbidden:
                    bad.append(f"{path.relative_to(ROOT)}:{line} imports {name}")
    assert not bad, "\n".join(bad)


def test_the_core_names_no_module_above_it_in_strings():
    """Schemes, scenarios and commands above the core register through entry points, not strings in twin/."""
    bad = []
    for path in sorted((ROOT / "twin").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Constant) and isinstance(node.value, str):
                text = node.value.strip()
                if any(text.startswith(f"{p}.") or text.startswith(f"{p}:") for p in FORBIDDEN["twin"]):
                    bad.append(f"{path.relative_to(ROOT)}:{node.lineno} {text!r}")
    assert not bad, "\n".join(bad)


BLOCK = f"""
import importlib, importlib.abc, pkgutil, sys
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in {OPTIONAL!r}:
            raise ModuleNotFoundError(f"No module named {{name!r}}", name=name)
sys.meta_path.insert(0, Block())
import twin
names = [m.name for m in pkgutil.walk_packages(twin.__path__, "twin.") if not m.name.endswith("__main__")]
for name in names:
    importlib.import_module(name)
assert not any(m.split(".")[0] in {OPTIONAL!r} for m in sys.modules), "an optional package got imported"
print(len(names))
"""


def test_every_twin_module_imports_without_the_optional_packages():
    out = subprocess.run([sys.executable, "-c", BLOCK], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert out.returncode == 0, out.stderr
    assert int(out.stdout.strip()) > 30


def test_a_command_that_needs_a_missing_extra_says_which_in_one_line():
    code = BLOCK.split("import twin\n")[0] + "from twin.cli import main\nsys.exit(main(sys.argv[1:]))\n"
    out = subprocess.run([sys.executable, "-c", code, "run", "static-shapes"], capture_output=True, text=True,
                         cwd=ROOT, timeout=120)
    assert out.returncode == 2, out.stderr
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and "'sim' extra" in lines[0], out.stderr
    # the hint installs the way the README does, from a checkout (issue 23 A11), and the README quotes it
    assert lines[0].endswith("pip install '.[sim]' from a catheter-twin checkout"), lines[0]
    readme = " ".join((ROOT / "README.md").read_text(encoding="utf-8").split())
    assert lines[0] in readme


def test_no_scenario_imports_another():
    """Scenarios share code through scenarios/_common and scenarios/report.py only."""
    shared = {"scenarios._common", "scenarios.report", "scenarios.studies"}
    bad = []
    for path in sorted((ROOT / "scenarios").glob("*.py")):
        for line, name in _imports(path):
            if name.startswith("scenarios.") and not any(name == s or name.startswith(s + ".") for s in shared):
                bad.append(f"{path.relative_to(ROOT)}:{line} imports {name}")
    assert not bad, "\n".join(bad)


# ------------------------------------------------------------------------------------------ inside twin


def _twin_modules() -> dict[str, Path]:
    mods = {}
    for path in sorted((ROOT / "twin").rglob("*.py")):
        name = ".".join(path.relative_to(ROOT).with_suffix("").parts)
        mods[name.removesuffix(".__init__")] = path
    return mods


def _twin_graph() -> dict[str, set[str]]:
    """module → the twin modules it imports (at the top or inside functions; ``from pkg import mod`` names the
    submodule, ``from pkg import name`` the package's face)."""
    mods = _twin_modules()
    graph: dict[str, set[str]] = {m: set() for m in mods}
    for m, path in mods.items():
        pkg = m if path.name == "__init__.py" else m.rpartition(".")[0]
        tree = ast.parse(path.read_text())
        typing_only = {id(n) for block in ast.walk(tree) if isinstance(block, ast.If)
                       and ast.unparse(block.test) in ("TYPE_CHECKING", "typing.TYPE_CHECKING")
                       for n in ast.walk(block)}  # never run: no runtime cycle
        for node in ast.walk(tree):
            if id(node) in typing_only:
                continue
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    parts = pkg.split(".")[: len(pkg.split(".")) - node.level + 1]
                    base = ".".join(parts + ([base] if base else []))
                names = [f"{base}.{a.name}" if f"{base}.{a.name}" in mods else base for a in node.names]
            else:
                continue
            for n in names:
                while n and n not in mods:
                    n = n.rpartition(".")[0]
                if n and n != m:
                    graph[m].add(n)
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    sys.setrecursionlimit(10_000)
    for v in graph:
        if v not in index:
            visit(v)
    return out


def _is_a_face_and_its_modules(comp: list[str], graph: dict[str, set[str]]) -> bool:
    # a package's face imports its modules: a cycle of a face and ITS modules is how a face works, provided none
    # of those modules imports the face back (that would be a real cycle: faces are for the package's users)
    top = min(comp, key=len)
    own = all(m == top or m.startswith(top + ".") for m in comp)
    return own and not any(top in graph[m] for m in comp if m != top)


def test_no_import_cycle_inside_twin():
    graph = _twin_graph()
    cycles = [c for c in _cycles(graph) if not _is_a_face_and_its_modules(c, graph)]
    assert not cycles, "\n".join(" <-> ".join(c) for c in cycles)


#: what twin/io may import of the rest of twin: the data types, the models it stores, the registry, the version,
#: and SO(3) conversions (a leaf of numpy alone: rotations to quaternions for the ROS messages)
IO_MAY_IMPORT = {"twin", "twin.frames", "twin.fiber", "twin.calibration", "twin.extras", "twin.registry",
                 "twin._validate", "twin.so3"}


def test_io_imports_nothing_above_itself():
    """twin/io holds I/O only (codecs, transports, drivers, recordings, logs): nothing of the loop, the commands,
    the viewer, OpenIGTLink, the benches, the reconstruction or the scoring."""
    bad = [f"{m} -> {n}" for m, ns in _twin_graph().items() if m.startswith("twin.io.") or m == "twin.io"
           for n in ns if not (n == "twin.io" or n.startswith("twin.io.") or n in IO_MAY_IMPORT)]
    assert not bad, "\n".join(bad)
    above = ("twin.live", "twin.cli", "twin.viewer", "twin.igtl", "twin.bench", "twin.reconstruct", "twin.metrics",
             "twin.spun", "twin.strain", "twin.curve")
    assert not any(a in IO_MAY_IMPORT for a in above)


# ---------------------------------------------------------------------------------- the source protocol


def _source_classes() -> dict[str, type]:
    """scheme → the class its registered opener returns (its return annotation)."""
    import typing

    from twin import registry
    from twin.io.source import schemes

    out = {}
    for scheme in schemes():
        opener = registry.load("twin.sources", scheme)
        out[scheme] = typing.get_type_hints(opener)["return"]
    return out


def test_every_registered_source_satisfies_the_source_protocol():
    import inspect
    import typing

    from twin.io.source import Source

    classes = _source_classes()
    assert {"illumisense", "fispec", "hyperion", "replay", "synthetic", "sim"} <= set(classes)
    members = {n for n in dir(Source) if not n.startswith("_")} & set(typing.get_type_hints(Source)) | {
        "read_batch", "stats", "describe", "close"}
    proto = inspect.signature(Source.read_batch)
    for scheme, cls in classes.items():
        for name in members:
            assert hasattr(cls, name), f"{scheme}: {cls.__name__} has no {name}"
        impl = cls.read_batch
        assert impl is not Source.read_batch, f"{scheme}: {cls.__name__} does not implement read_batch"
        params = list(inspect.signature(impl).parameters)
        assert params[:3] == list(proto.parameters), f"{scheme}: {cls.__name__}.read_batch{inspect.signature(impl)}"
        assert typing.get_type_hints(impl).get("return") == typing.get_type_hints(Source.read_batch)["return"], scheme


def test_sources_deliver_one_batch_form(tmp_path):
    """Opened for real: every read is one 1-D batch Frame (a single frame is a batch of one) or None."""
    from twin.frames import Frame
    from twin.io.record import Recorder
    from twin.io.source import Source, open_source

    src = open_source("synthetic://?pace=max&frames=50")
    path = tmp_path / "r.h5"
    with Recorder(path, fiber=src.fiber) as rec:
        rec.append(src.read_batch(50, 1.0))
    sources = [open_source("synthetic://?pace=max&frames=50"), open_source(f"replay://{path}?speed=max")]
    for s in sources:
        assert isinstance(s, Source)
        with s:
            one = s.read_batch(1, 1.0)
            more = s.read_batch(30, 1.0)
        for b in (one, more):
            assert isinstance(b, Frame) and len(b.batch_shape) == 1
        assert len(one) == 1 and 1 <= len(more) <= 30 and more.sequence[0] == one.sequence[0] + 1


def test_every_opener_uses_the_option_parser():
    """Options are parsed one way (twin/io/options.py): every registered opener calls parse_options."""
    import inspect

    from twin import registry
    from twin.io.source import schemes

    for scheme in schemes():
        source = inspect.getsource(registry.load("twin.sources", scheme))
        assert "parse_options(" in source, f"{scheme}:// parses its options its own way"
