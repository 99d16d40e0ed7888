#!/usr/bin/env python3
"""Check a checkout of docker/jetson/jazzy.repos for what the Jetson build stage meets on Ubuntu 20.04.

    vcs import src < docker/jetson/jazzy.repos          # on a machine that reaches GitHub
    .venv/bin/python docker/jetson/check_jazzy_sources.py src [--python38 .venv38/bin/python]

Reports, without building anything:

1. the dependency closure of the packages the image builds (`ROS_PACKAGES` of the Dockerfile):
   every ROS package it needs must be in the checkout; the keys it needs from the system are
   listed (the Dockerfile's apt/pip lists must cover them);
2. the Python of the packages in that closure (tests excluded): vermin for Python 3.8
   (annotations evaluated), and a compile under a real Python 3.8 when one is given;
3. the highest `cmake_minimum_required` in the closure (Ubuntu 20.04 has CMake 3.16);
4. whether each patch in docker/jetson/patches applies (`git apply --check`).

Exit status 0 when the closure is complete and the Python check is clean (after patches), 1
otherwise. It runs on the project's venv (catkin_pkg, vermin) with the checkout's files only.
"""
from __future__ import annotations

import argparse
import glob
import os
import re
import shlex
import subprocess
import sys
from typing import Dict, List, Set, Tuple

HERE = os.path.dirname(os.path.abspath(__file__))
DEP_KINDS = ("build_depends", "buildtool_depends", "build_export_depends", "buildtool_export_depends",
             "exec_depends")
CONDITIONS = {"ROS_VERSION": "2", "ROS_DISTRO": "jazzy", "ROS_PYTHON_VERSION": "3", "PLATFORM": "linux"}


# Files vermin flags that are fine on Python 3.8, each checked by reading it (release-jazzy-20241223):
# path suffix -> why. They are left out of the check and listed with the reason instead.
KNOWN_FINE = {
    "ros2/rclpy/rclpy/rclpy/clock.py": "imports typing.TypeAlias under `if TYPE_CHECKING:` only",
    "ros2/rclpy/rclpy/rclpy/qos_overriding_options.py": "imports typing.TypeAlias under `if TYPE_CHECKING:` only",
    "ros2/rclpy/rclpy/rclpy/time_source.py": "weakref.ReferenceType[...] annotates an attribute inside a method: "
                                             "never evaluated (PEP 526)",
    "ament/ament_package/ament_package/templates.py": "calls importlib.resources.files behind hasattr(), else path()",
    "ament/ament_lint/ament_cpplint/ament_cpplint/cpplint.py": "Python 2 branches behind version checks; a linter "
                                                              "that only tests run",
    "ament/googletest/": "googletest's Python 2 maintenance scripts: never run by a build or the graph",
}


def known_fine(path: str) -> str:
    normalized = path.replace(os.sep, "/")
    return next((why for suffix, why in KNOWN_FINE.items()
                 if normalized.endswith(suffix) or ("/" + suffix) in normalized and suffix.endswith("/")), "")


def dockerfile_packages() -> List[str]:
    """The ROS_PACKAGES build argument of the Dockerfile (the packages the image builds up to)."""
    with open(os.path.join(HERE, "Dockerfile"), encoding="utf-8") as stream:
        text = stream.read()
    match = re.search(r'ARG ROS_PACKAGES="([^"]+)"', text)
    if not match:
        raise SystemExit("no ARG ROS_PACKAGES=\"...\" in docker/jetson/Dockerfile")
    return match.group(1).split()


def read_packages(src: str) -> Dict[str, Tuple[str, Set[str]]]:
    """name -> (folder, the names it depends on to build and run), conditions evaluated for Jazzy."""
    from catkin_pkg.package import parse_package

    packages: Dict[str, Tuple[str, Set[str]]] = {}
    for xml in sorted(glob.glob(os.path.join(src, "**", "package.xml"), recursive=True)):
        folder = os.path.dirname(xml)
        if any(os.path.exists(os.path.join(folder, marker)) for marker in ("COLCON_IGNORE", "AMENT_IGNORE")):
            continue
        package = parse_package(folder)
        package.evaluate_conditions(CONDITIONS)
        deps = {dep.name for kind in DEP_KINDS for dep in getattr(package, kind) if dep.evaluated_condition}
        packages[package.name] = (folder, deps)
    return packages


def closure(packages: Dict[str, Tuple[str, Set[str]]], targets: List[str]) -> Tuple[List[str], Set[str], List[str]]:
    """(workspace packages needed, system keys needed, targets missing from the checkout)."""
    missing = [t for t in targets if t not in packages]
    needed: Set[str] = set()
    system: Set[str] = set()
    todo = [t for t in targets if t in packages]
    while todo:
        name = todo.pop()
        if name in needed:
            continue
        needed.add(name)
        for dep in packages[name][1]:
            if dep in packages:
                todo.append(dep)
            else:
                system.add(dep)
    return sorted(needed), system, missing


def python_files(folders: List[str]) -> List[str]:
    files = []
    for folder in folders:
        for path in glob.glob(os.path.join(folder, "**", "*.py"), recursive=True):
            parts = set(path.split(os.sep))
            if parts & {"test", "tests", "doc", "docs", "examples"}:
                continue
            files.append(path)
    return sorted(files)


def run_vermin(files: List[str]) -> Tuple[int, str]:
    vermin = os.path.join(os.path.dirname(sys.executable), "vermin")
    if not files:
        return 0, ""
    result = subprocess.run([vermin, "-q", "-t=3.8-", "--no-tips", "--violations", "--eval-annotations"] + files,
                            capture_output=True, text=True)
    return result.returncode, result.stdout + result.stderr


COMPILE_SCRIPT = """
import sys
paths = [p for p in sys.stdin.read().split('\\n') if p]
bad = []
for path in paths:
    try:
        with open(path, encoding='utf-8') as stream:
            compile(stream.read(), path, 'exec', dont_inherit=True)
    except SyntaxError as error:
        bad.append('%s: %s' % (path, error))
print('Python %s compiled %d files, %d syntax errors' % (sys.version.split()[0], len(paths), len(bad)))
print('\\n'.join(bad))
"""


def compile_py38(python38: str, files: List[str]) -> str:
    """Compile every file with a real Python 3.8 (catches 3.9+ grammar vermin may not know)."""
    result = subprocess.run([python38, "-c", COMPILE_SCRIPT], input="\n".join(files), capture_output=True, text=True)
    return (result.stdout + result.stderr).strip()


def cmake_minimums(folders: List[str]) -> List[Tuple[str, str]]:
    found = []
    for folder in folders:
        path = os.path.join(folder, "CMakeLists.txt")
        if not os.path.exists(path):
            continue
        with open(path, encoding="utf-8", errors="replace") as stream:
            match = re.search(r"cmake_minimum_required\s*\(\s*VERSION\s+([0-9.]+)", stream.read(), re.IGNORECASE)
        if match:
            found.append((match.group(1), os.path.basename(folder)))
    return sorted(found, key=lambda item: tuple(int(x) for x in item[0].split(".")), reverse=True)


def check_patches(src: str) -> List[str]:
    lines = []
    for patch in sorted(glob.glob(os.path.join(HERE, "patches", "*.patch"))):
        with open(patch, encoding="utf-8") as stream:
            target = next((line.split(":", 1)[1].strip() for line in stream if line.startswith("Repository:")), "")
        repo_dir = os.path.join(src, target)
        result = subprocess.run(["git", "apply", "--check", patch], cwd=repo_dir, capture_output=True,
                                text=True) if os.path.isdir(repo_dir) else None
        status = "applies" if result is not None and result.returncode == 0 else "DOES NOT APPLY"
        lines.append("%s -> %s: %s" % (os.path.basename(patch), target or "?", status))
    return lines


def write_index(src: str, path: str) -> None:
    """Repository (the .repos key) -> version and the packages in it: what the CI test maps imports with."""
    import yaml

    with open(os.path.join(HERE, "jazzy.repos"), encoding="utf-8") as stream:
        repos = yaml.safe_load(stream)["repositories"]
    index = {}
    for key, spec in repos.items():
        folder = os.path.join(src, key)
        names = []
        for xml in glob.glob(os.path.join(folder, "**", "package.xml"), recursive=True):
            with open(xml, encoding="utf-8") as stream:
                match = re.search(r"<name>\s*([^<\s]+)\s*</name>", stream.read())
            if match:
                names.append(match.group(1))
        index[key] = {"version": spec["version"], "packages": sorted(names)}
    header = ("# Generated by docker/jetson/check_jazzy_sources.py --write-index from a checkout of jazzy.repos:\n"
              "# the ROS packages each repository holds. tests/test_jetson_image.py maps the robot packages'\n"
              "# imports and package.xml dependencies to repositories with it.\n")
    with open(path, "w", encoding="utf-8") as stream:
        stream.write(header + yaml.safe_dump({"repositories": index}, sort_keys=True, width=100))
    count = sum(len(entry["packages"]) for entry in index.values())
    print("wrote %s: %d repositories, %d packages" % (path, len(index), count))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("src", help="folder the .repos file was imported into")
    parser.add_argument("--python38", default="", help="a Python 3.8 interpreter to compile the sources with")
    parser.add_argument("--write-index", default="", help="write the package index (repository -> its packages, "
                        "docker/jetson/jazzy_packages.yaml) of this checkout")
    args = parser.parse_args()
    if args.write_index:
        write_index(args.src, args.write_index)
    targets = dockerfile_packages()
    packages = read_packages(args.src)
    needed, system, missing = closure(packages, targets)
    print("packages in the checkout: %d; the image builds %d (up to %d targets)" % (len(packages), len(needed),
                                                                                     len(targets)))
    print("targets missing from the checkout: %s" % (", ".join(missing) or "none"))
    print("system keys of the closure: %s" % " ".join(sorted(system)))
    folders = [packages[name][0] for name in needed]
    all_files = python_files(folders)
    files = [path for path in all_files if not known_fine(path)]
    for path in all_files:
        if known_fine(path) and not path.replace(os.sep, "/").count("/googletest/"):
            print("known fine on 3.8: %s (%s)" % (os.path.relpath(path, args.src), known_fine(path)))
    skipped = len(all_files) - len(files)
    print("left out as known fine: %d files (googletest scripts included)" % skipped)
    status, report = run_vermin(files)
    print("vermin (Python 3.8, annotations evaluated) on %d files: %s" % (len(files), "clean" if status == 0
                                                                          else "violations"))
    if report.strip():
        print(report.rstrip())
    if args.python38:
        print("compile under %s: %s" % (shlex.quote(args.python38), compile_py38(args.python38, files) or "ok"))
    print("highest cmake_minimum_required: %s" % ", ".join("%s (%s)" % item for item in cmake_minimums(folders)[:4]))
    for line in check_patches(args.src):
        print("patch " + line)
    return 0 if not missing and status == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
