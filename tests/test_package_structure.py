"""The packages import one way, and each package.xml declares what its package imports.

Every module under src/<package>/<package>/ is parsed (imports inside functions included); a
module may import its own package and packages of a lower layer only. docs/ARCHITECTURE.md
explains the layers. Tests (src/*/test, tests/) are not checked: they may use anything below or
beside what they test.
"""
from __future__ import annotations

import ast
import sys
import xml.etree.ElementTree as ElementTree
from pathlib import Path
from typing import Dict, Iterator, Set, Tuple

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
        if module in ("__future__", "setuptools"):
            continue
        key = THIRD_PARTY_KEYS.get(module, module)
        if key not in declared:
            missing.append(f"{key} (imported at {sorted(places)[0]})")
    assert not missing, f"{package_dir.name}/package.xml does not declare: " + ", ".join(missing)


def test_the_checker_sees_function_level_imports(tmp_path: Path) -> None:
    module = tmp_path / "m.py"
    module.write_text("def f():\n    from leapnbv_evaluation import report\n")
    assert list(module_imports(module)) == [("leapnbv_evaluation", 2)]
