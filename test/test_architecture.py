"""doc/ARCHITECTURE.md stays true: every module is named there, and the core's import rules hold; package.xml
declares what the package imports.

Imports are read from the source with ``ast``; no module is imported.
"""

import ast
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "sonar_ring"
DOC = ROOT / "doc" / "ARCHITECTURE.md"

ROS_PACKAGES = {"rclpy", "rcl_interfaces", "builtin_interfaces", "rosbags", "launch", "launch_ros",
                "sonar_ring.msg", "sonar_ring.ros"}
"""Imports that belong to the ROS layer (with every ``*_msgs`` package)."""

LAZY_ROS_IMPORTS = {
    "cli.py": {"sonar_ring.ros"},  # `process` and `record-sim` load sonar_ring.ros.offline when run
    "benchmark/graph.py": {"rclpy", "sonar_ring.msg", "sonar_ring.ros", "_msgs"},  # runs the node graph
    "benchmark/measure.py": {"rclpy"},  # probes for rclpy before the graph row
}
"""The modules outside ``sonar_ring/ros/`` that may import the ROS layer inside a function, and what."""


def modules() -> list[Path]:
    """Every module of the package but the ``__init__.py`` files."""
    return sorted(path for path in PACKAGE.rglob("*.py") if path.name != "__init__.py")


def relative(path: Path) -> str:
    """``ros/driver.py`` for ``sonar_ring/ros/driver.py``: how the document names a module."""
    return path.relative_to(PACKAGE).as_posix()


def dotted(path: Path) -> str:
    """The module's import name, ``sonar_ring.ros.driver``."""
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports(path: Path) -> list[tuple[str, bool]]:
    """``(module, at_module_level)`` for every import of ``path``, ``importlib.import_module("...")`` included.

    ``from a import b`` gives ``a.b`` (which may be a module or a name in ``a``).
    """
    found = []

    def visit(node: ast.AST, top: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.Import):
                found.extend((alias.name, top) for alias in child.names)
            elif isinstance(child, ast.ImportFrom):
                assert child.level == 0, f"{path}: relative import"
                found.extend((f"{child.module}.{alias.name}", top) for alias in child.names)
            elif (isinstance(child, ast.Call) and isinstance(child.func, ast.Attribute)
                  and child.func.attr == "import_module" and child.args
                  and isinstance(child.args[0], ast.Constant) and isinstance(child.args[0].value, str)):
                found.append((child.args[0].value, top))
            visit(child, top and not isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda))

    visit(ast.parse(path.read_text(encoding="utf-8"), str(path)), True)
    return found


def ros_part(name: str) -> str | None:
    """The ROS package ``name`` belongs to (``_msgs`` for any message package), or None."""
    for package in ROS_PACKAGES:
        if name == package or name.startswith(package + "."):
            return package
    if name.split(".")[0].endswith("_msgs"):
        return "_msgs"
    return None


def test_every_module_is_named_in_the_architecture():
    text = DOC.read_text(encoding="utf-8")
    missing = [relative(path) for path in modules() if f"`{relative(path)}`" not in text]
    assert not missing, f"doc/ARCHITECTURE.md does not name these modules (as `path` under sonar_ring/): {missing}"


def test_the_architecture_links_only_inside_the_repository():
    text = DOC.read_text(encoding="utf-8")
    for target in re.findall(r"\]\(([^)]+)\)", text):
        if target.startswith("#"):
            continue
        assert "://" not in target, f"doc/ARCHITECTURE.md links outside the repository: {target}"
        assert (DOC.parent / target.split("#")[0]).resolve().is_relative_to(ROOT), target
        assert (DOC.parent / target.split("#")[0]).exists(), f"doc/ARCHITECTURE.md: broken link {target}"


def test_the_core_never_imports_rclpy():
    """Outside ``sonar_ring/ros/`` nothing imports rclpy, messages or the ROS layer at module level.

    Inside a function only the modules of :data:`LAZY_ROS_IMPORTS` may, and only what is listed there.
    """
    wrong = []
    for path in modules():
        name = relative(path)
        if name.startswith("ros/"):
            continue
        allowed = LAZY_ROS_IMPORTS.get(name, set())
        for module, top in imports(path):
            part = ros_part(module)
            if part is not None and (top or part not in allowed):
                wrong.append(f"{name}: {module}{'' if top else ' (in a function)'}")
    assert not wrong, f"the core imports the ROS layer: {wrong}"


def test_no_import_cycles():
    """Module-level imports between the package's modules form no cycle."""
    by_name = {dotted(path): path for path in PACKAGE.rglob("*.py")}
    graph = {}
    for name, path in by_name.items():
        targets = set()
        for module, top in imports(path):
            if not top or not module.startswith("sonar_ring"):
                continue
            while module not in by_name and "." in module:  # `from sonar_ring.x import name`
                module = module.rsplit(".", 1)[0]
            if module in by_name and module != name and module != "sonar_ring":
                targets.add(module)
        graph[name] = targets
    state: dict[str, int] = {}
    cycles = []

    def visit(name: str, stack: list[str]) -> None:
        state[name] = 1
        stack.append(name)
        for target in sorted(graph[name]):
            if state.get(target) == 1:
                cycles.append(stack[stack.index(target):] + [target])
            elif target not in state:
                visit(target, stack)
        stack.pop()
        state[name] = 2

    for name in sorted(graph):
        if name not in state:
            visit(name, [])
    assert not cycles, f"import cycles: {cycles}"


THIRD_PARTY_KEYS = {
    "numpy": "python3-numpy", "numba": "python3-numba", "yaml": "python3-yaml", "serial": "python3-serial",
    "gtsam": "python3-gtsam-pip", "rosbags": "python3-rosbags-pip", "tqdm": "python3-tqdm",
    "matplotlib": "python3-matplotlib", "scipy": "python3-scipy", "mpmath": "python3-mpmath",
    "hypothesis": "python3-hypothesis", "pytest": "python3-pytest",
}
"""The rosdep key of each third-party module the package or its tests import (rosdistro's, or rosdep.yaml's)."""
UNDECLARED = {"psutil"}
"""Imported only where installed: the SLAM cost benchmark reads memory from /proc without it."""


def declared_keys() -> dict[str, set[str]]:
    """package.xml's rosdep keys: ``run`` (depend, exec_depend) and ``test`` (those and test_depend)."""
    text = (ROOT / "package.xml").read_text(encoding="utf-8")
    tagged = {tag: set(re.findall(rf"<{tag}>([^<]+)</{tag}>", text)) for tag in ("depend", "exec_depend",
                                                                                  "test_depend")}
    run = tagged["depend"] | tagged["exec_depend"]
    return {"run": run, "test": run | tagged["test_depend"]}


def needed_key(module: str) -> str | None:
    """The rosdep key an import needs (None: the standard library, this package, or a test helper)."""
    top = module.split(".")[0]
    if top in sys.stdlib_module_names or top == "sonar_ring" or (ROOT / "test" / f"{top}.py").exists():
        return None
    if top in UNDECLARED:
        return None
    if top in THIRD_PARTY_KEYS:
        return THIRD_PARTY_KEYS[top]
    if ros_part(module) is not None or top.endswith("_interfaces") or top.startswith("launch") or top in (
            "ament_index_python", "rclpy"):
        return top
    raise AssertionError(f"no rosdep key known for the import of {module!r}: add it to THIRD_PARTY_KEYS")


def test_package_xml_declares_what_the_package_imports():
    """Every module the package, its launch file and its tests import has its rosdep key in package.xml.

    ``rosdep install --from-paths src`` then installs what a robot runs (the tests' keys as test_depend),
    and rosdep.yaml defines only keys package.xml uses.
    """
    declared = declared_keys()
    missing = set()
    for scope, paths in (("run", [*modules(), *(ROOT / "launch").glob("*.py")]),
                         ("test", sorted((ROOT / "test").glob("*.py")))):
        for path in paths:
            for module, _ in imports(path):
                key = needed_key(module)
                if key is not None and key not in declared[scope] and key != "sonar_ring":
                    missing.add(f"{key} ({scope}: {path.relative_to(ROOT)} imports {module})")
    assert not missing, f"package.xml lacks these rosdep keys: {sorted(missing)}"
    custom = set(re.findall(r"^([\w-]+):", (ROOT / "rosdep.yaml").read_text(encoding="utf-8"), re.MULTILINE))
    assert custom <= declared["test"], f"rosdep.yaml defines keys package.xml does not use: {custom - declared['test']}"


def _kernels(tree: ast.Module) -> list[ast.FunctionDef]:
    """The module's functions marked ``@kernel`` or ``@kernel(...)``."""
    def is_kernel(decorator) -> bool:
        target = decorator.func if isinstance(decorator, ast.Call) else decorator
        return isinstance(target, ast.Name) and target.id == "kernel"
    return [node for node in tree.body
            if isinstance(node, ast.FunctionDef) and any(map(is_kernel, node.decorator_list))]


def test_a_kernel_calls_kernels_of_its_own_module_only():
    """numba's cache of a kernel holds its callees' code and is invalidated by its own file's changes alone."""
    kernels = {path: _kernels(ast.parse(path.read_text())) for path in modules()}
    names = {dotted(path).rsplit(".", 1)[-1]: {kernel.name for kernel in found} for path, found in kernels.items()}
    crossing = []
    for path, found in kernels.items():
        for kernel in found:
            for node in ast.walk(kernel):
                if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                        and isinstance(node.func.value, ast.Name)
                        and node.func.attr in names.get(node.func.value.id, ())):
                    crossing.append(f"{relative(path)}: {kernel.name} calls {node.func.value.id}.{node.func.attr}")
    assert not crossing, crossing
