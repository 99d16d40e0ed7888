"""Imports go one way, each package.xml declares what its package imports, and cores are ROS-free.

Every module under src/<package>/<package>/ is parsed (imports inside functions included); a
module may import its own package and packages of a lower layer only. docs/ARCHITECTURE.md
explains the layers. A core module (any module outside a ``nodes/`` folder and outside the ROS
glue listed in ``ROS_GLUE``) imports neither rclpy nor a message package. Tests (src/*/test,
tests/) are not checked: they may use anything below or beside what they test. Every
``from leapnbv_<package>... import name`` (in the packages, scripts/, tools/ and tests/) must name
something its module defines: an import inside a function fails only when the function runs.
"""
from __future__ import annotations

import ast
import sys
import xml.etree.ElementTree as ElementTree
from pathlib import Path
from typing import Dict, Iterator, List, Set, Tuple

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"

# Layer of each package: a module may import packages of a strictly lower layer (and its own).
LAYERS: Dict[str, int] = {
    "leapnbv_msgs": 0,
    "leapnbv_common": 1,
    "leapnbv_perception": 2,
    "leapnbv_geometry": 2,
    "leapnbv_planner": 2,
    "leapnbv_bags": 2,
    "leapnbv_stand_ins": 3,
    "leapnbv_sim": 4,
    "leapnbv_bringup": 5,
    "leapnbv_evaluation": 6,
}

# Third-party Python modules -> the package.xml key that provides them.
THIRD_PARTY_KEYS = {
    "numpy": "python3-numpy",
    "cv2": "python3-opencv",
    "numba": "python3-numba",
    "onnxruntime": "python3-onnxruntime",
    "onnx": "python3-onnx",
    "rosbags": "python3-rosbags",
    "mcap": "python3-mcap",
    "matplotlib": "python3-matplotlib",
    "yaml": "python3-yaml",
}
# The TensorRT adapter imports these only on the Jetson, where JetPack's base image provides them
# (no rosdep key exists for them); everywhere else the backend is never selected.
PROVIDED_BY_JETPACK = {"tensorrt", "pycuda", "cuda"}


def package_dirs() -> Iterator[Path]:
    for xml in sorted(SRC.glob("*/package.xml")):
        yield xml.parent


def module_imports(path: Path) -> Iterator[Tuple[str, int]]:
    """(top-level module name, line) of every absolute import in a file."""
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name.split(".")[0], node.lineno
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            yield node.module.split(".")[0], node.lineno


def python_files(package_dir: Path) -> Iterator[Path]:
    code = package_dir / package_dir.name
    yield from sorted(code.rglob("*.py")) if code.is_dir() else []
    for extra in ("launch", "scripts"):
        yield from sorted((package_dir / extra).glob("*.py"))


def imported_modules(package_dir: Path) -> Dict[str, Set[str]]:
    """Top-level module -> the places (file:line) in the package that import it."""
    found: Dict[str, Set[str]] = {}
    for path in python_files(package_dir):
        for module, line in module_imports(path):
            found.setdefault(module, set()).add(f"{path.relative_to(SRC)}:{line}")
    return found


def declared_dependencies(package_dir: Path) -> Set[str]:
    root = ElementTree.parse(package_dir / "package.xml").getroot()
    tags = ("depend", "exec_depend", "build_export_depend")
    return {element.text.strip() for tag in tags for element in root.iter(tag) if element.text}


def test_every_package_has_a_layer() -> None:
    assert {d.name for d in package_dirs()} == set(LAYERS)


@pytest.mark.parametrize("package_dir", list(package_dirs()), ids=lambda d: d.name)
def test_imports_go_one_way(package_dir: Path) -> None:
    own = LAYERS[package_dir.name]
    wrong = []
    for module, places in imported_modules(package_dir).items():
        if module in LAYERS and module != package_dir.name and LAYERS[module] >= own:
            wrong.extend(f"{place} imports {module} (layer {LAYERS[module]} >= {own})" for place in sorted(places))
    assert not wrong, "imports against the direction:\n" + "\n".join(wrong)


@pytest.mark.parametrize("package_dir", list(package_dirs()), ids=lambda d: d.name)
def test_package_xml_declares_what_the_package_imports(package_dir: Path) -> None:
    declared = declared_dependencies(package_dir)
    stdlib = set(getattr(sys, "stdlib_module_names", ()))
    missing = []
    for module, places in sorted(imported_modules(package_dir).items()):
        if module == package_dir.name or module in stdlib or module in PROVIDED_BY_JETPACK:
            continue
        if module in ("__future__", "setuptools", "_typeshed"):  # _typeshed: the type checker's, under TYPE_CHECKING
            continue
        key = THIRD_PARTY_KEYS.get(module, module)
        if key not in declared:
            missing.append(f"{key} (imported at {sorted(places)[0]})")
    assert not missing, f"{package_dir.name}/package.xml does not declare: " + ", ".join(missing)


def test_the_checker_sees_function_level_imports(tmp_path: Path) -> None:
    module = tmp_path / "m.py"
    module.write_text("def f():\n    from leapnbv_evaluation import report\n")
    assert list(module_imports(module)) == [("leapnbv_evaluation", 2)]


# Modules outside nodes/ that are ROS glue by design (dotted names; a name covers its submodules).
# Everything else under src/<package>/<package>/ is a core: plain Python and numpy.
ROS_GLUE: Dict[str, str] = {
    "leapnbv_common.conversions": "the one place where messages become arrays and back",
    "leapnbv_common.qos": "the QoS profiles (rclpy.qos) every node and tool subscribes with",
    "leapnbv_common.node_params": "declares a node's parameters and spins it (rclpy)",
    "leapnbv_common.diagnostics": "builds the /diagnostics messages of every node",
    "leapnbv_common.pulled_input": "subscriptions a node reads on demand (rclpy callback groups)",
    "leapnbv_common.camera_pose": "the camera-pose sources: pose and TF messages in, poses out",
    "leapnbv_common.managed_node": "the lifecycle (managed) node every stage node is",
    "leapnbv_common.stage_inputs": "the stage helper's per-input converters: messages in, arrays out",
    "leapnbv_common.mesh_faces_topic": "the mesh_faces topic: a model's triangles published once and kept by id",
    "leapnbv_perception.backends.ground_truth": "reads the simulator's ground-truth messages in place of engines",
    "leapnbv_sim.frame_messages": "the messages a camera driver publishes for a rendered frame (node and bags)",
    "leapnbv_bringup": "starts, supervises and replays the graph: all of it talks to ROS",
    "leapnbv_evaluation.harness": "the evaluation's ROS session: drives the graph episode by episode",
    "leapnbv_evaluation.demo": "runs the graph on a bag and reads its messages back for the report",
}
# Top-level modules that are ROS itself; besides these, any *_msgs, *_srvs or *_interfaces package.
ROS_MODULES = {"rclpy", "rosidl_runtime_py", "launch", "launch_ros", "tf2_ros", "message_filters", "rosbag2_py"}


def is_ros_module(top_level: str) -> bool:
    """Whether a top-level module is rclpy, another ROS client module or a message package."""
    return top_level in ROS_MODULES or top_level.endswith(("_msgs", "_srvs", "_interfaces"))


def module_name(path: Path) -> str:
    """Dotted name of a file under src/<package>/: its module name, or <package>.launch.<file> and the like."""
    parts = list(path.relative_to(SRC).with_suffix("").parts)
    if parts[1] == parts[0]:  # the package's code folder: its modules' own names
        parts = parts[1:]
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def glue_entry(name: str) -> str:
    """The ROS_GLUE entry that covers a dotted module name, or ''."""
    for entry in ROS_GLUE:
        if name == entry or name.startswith(entry + "."):
            return entry
    return ""


def is_core(path: Path) -> bool:
    return "nodes" not in path.relative_to(SRC).parts and not glue_entry(module_name(path))


def all_python_files() -> List[Path]:
    return [path for package_dir in package_dirs() for path in python_files(package_dir)]


def test_no_core_module_imports_ros() -> None:
    wrong = []
    for path in all_python_files():
        if not is_core(path):
            continue
        for module, line in module_imports(path):
            if is_ros_module(module):
                wrong.append(f"{path.relative_to(SRC)}:{line} imports {module}")
    assert not wrong, (
        "core modules (outside nodes/ and ROS_GLUE) import ROS; move that code into a node or the glue:\n"
        + "\n".join(wrong)
    )


def test_every_ros_glue_entry_is_glue() -> None:
    # An entry whose modules no longer import ROS is a core again and leaves the list.
    names = {module_name(path): path for path in all_python_files()}
    for entry, why in ROS_GLUE.items():
        covered = [path for name, path in names.items() if glue_entry(name) == entry]
        assert covered, f"ROS_GLUE names {entry} ({why}), which is no module under src/"
        assert any(is_ros_module(module) for path in covered for module, _ in module_imports(path)), (
            f"ROS_GLUE names {entry}, but none of its modules imports ROS: it is a core"
        )


def test_the_ros_checks_see_what_they_should(tmp_path: Path) -> None:
    assert is_ros_module("rclpy") and is_ros_module("sensor_msgs") and is_ros_module("leapnbv_msgs")
    assert is_ros_module("builtin_interfaces") and not is_ros_module("numpy")
    assert not is_core(SRC / "leapnbv_bringup" / "launch" / "leapnbv.launch.py")
    assert not is_core(SRC / "leapnbv_common" / "leapnbv_common" / "conversions" / "images.py")
    assert not is_core(SRC / "leapnbv_sim" / "leapnbv_sim" / "nodes" / "simulator_node.py")
    assert is_core(SRC / "leapnbv_sim" / "leapnbv_sim" / "sample_bags.py")
    assert is_core(SRC / "leapnbv_evaluation" / "leapnbv_evaluation" / "episode.py")


# ------------------------------------------------------------------ imports that name what exists

ROOT = SRC.parent
# Code outside the packages that imports them, often inside a function (tools run in their own environment,
# so their imports of the runtime packages are only executed when a command reaches them).
IMPORTING_OUTSIDE_SRC = ("scripts", "tools/leapnbv_model_tools", "tools/tests", "tests")


def module_file(dotted: str) -> Path:
    """The file of a runtime package's module (its __init__.py for a package), which may not exist."""
    parts = dotted.split(".")
    base = SRC.joinpath(parts[0], *parts)
    return base / "__init__.py" if base.is_dir() else base.with_suffix(".py")


def top_level_names(path: Path) -> Set[str]:
    """Names a module defines or imports at its top level (inside top-level if / try blocks too)."""
    names: Set[str] = {"__doc__", "__file__", "__name__"}
    body = list(ast.parse(path.read_text(), filename=str(path)).body)
    while body:
        node = body.pop()
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, (ast.Assign, ast.AnnAssign, ast.AugAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            names.update(n.id for target in targets for n in ast.walk(target) if isinstance(n, ast.Name))
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            names.update((alias.asname or alias.name).split(".")[0] for alias in node.names)
        elif isinstance(node, (ast.If, ast.Try)):
            body.extend(node.body + node.orelse + getattr(node, "finalbody", []))
            body.extend(n for handler in getattr(node, "handlers", []) for n in handler.body)
    return names


def missing_imported_names(path: Path) -> List[str]:
    """'file:line: module.name' for each `from leapnbv_<package>... import name` that names nothing there."""
    wrong = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if not (isinstance(node, ast.ImportFrom) and node.level == 0 and node.module):
            continue
        top = node.module.split(".")[0]
        if top not in LAYERS or top == "leapnbv_msgs":  # leapnbv_msgs is generated at build time
            continue
        target = module_file(node.module)
        where = f"{path.relative_to(ROOT) if ROOT in path.parents else path}:{node.lineno}"
        if not target.is_file():
            wrong.append(f"{where}: no module {node.module}")
            continue
        defined = top_level_names(target)
        for alias in node.names:
            submodule = module_file(f"{node.module}.{alias.name}")
            if alias.name not in defined and not submodule.is_file():
                wrong.append(f"{where}: {node.module} has no {alias.name}")
    return wrong


def test_every_project_import_names_what_exists() -> None:
    # An import inside a function fails only when that function runs: a tool's command or a benchmark that
    # no test reaches kept importing a helper after it moved to another package.
    files = [path for package_dir in package_dirs() for path in python_files(package_dir)]
    files += [path for folder in IMPORTING_OUTSIDE_SRC for path in sorted((ROOT / folder).rglob("*.py"))]
    wrong = [entry for path in files for entry in missing_imported_names(path)]
    assert not wrong, "imports of names that do not exist:\n" + "\n".join(wrong)


def test_the_import_check_sees_a_moved_name(tmp_path: Path) -> None:
    script = tmp_path / "s.py"
    script.write_text("def f():\n    from leapnbv_evaluation.metrics import pa_mpvpe_mm, is_success\n"
                      "    from leapnbv_common.procrustes import pa_mpvpe_mm\n"
                      "    from leapnbv_common import procrustes\n    from leapnbv_common.nowhere import x\n")
    found = [entry.split(": ", 1)[1] for entry in missing_imported_names(script)]
    assert found == ["leapnbv_evaluation.metrics has no pa_mpvpe_mm", "no module leapnbv_common.nowhere"]
