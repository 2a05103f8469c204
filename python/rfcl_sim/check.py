"""Verify that this interpreter has the simulator matrix rfcl was tested with.

Prints one line per package and exits 1 with the mismatches, so set-up fails early and clearly
instead of deep inside a simulator.
"""
import importlib.metadata as md
import sys

# package -> predicate on the installed version, and the requirement it stands for.
MATRIX = {
    "torch": (lambda v: v.split("+")[0] == "2.11.0", "==2.11.0 (matches tch 0.24)"),
    "mani_skill": (lambda v: v == "3.0.1", "==3.0.1"),
    "numpy": (lambda v: int(v.split(".")[0]) < 2, "<2 (mplib 0.1.1 segfaults on numpy 2)"),
    "metaworld": (lambda v: v == "3.1.1", "==3.1.1"),
    "gymnasium-robotics": (lambda v: v == "1.4.2", "==1.4.2"),
    "h5py": (lambda v: True, "any"),
    "opencv-python": (lambda v: v == "4.10.0.84", "==4.10.0.84 (accepts numpy 1)"),
}


def check() -> list[str]:
    problems = []
    for name, (ok, wanted) in MATRIX.items():
        try:
            version = md.version(name)
        except md.PackageNotFoundError:
            problems.append(f"{name}: not installed, expected {wanted}")
            continue
        if not ok(version):
            problems.append(f"{name}: {version} installed, expected {wanted}")
        else:
            print(f"  {name} {version}")
    return problems


def main() -> int:
    problems = check()
    for p in problems:
        print(f"rfcl_sim.check: {p}", file=sys.stderr)
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
