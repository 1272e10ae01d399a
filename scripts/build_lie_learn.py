"""Rebuild lie_learn 0.0.2 (an escnn dependency) against numpy 2.

Why this exists: every lie_learn wheel on PyPI is compiled
against numpy<2 and fails to import under numpy 2, yet the rest of our stack
(franky-sim via pin/cmeel-boost, rerun-sdk, pyarrow) requires numpy 2. The 0.0.2
wheel ships its Cython sources, so we take that wheel from the package registry,
patch the APIs that numpy 2 / SciPy 1.17 removed, recompile with Cython 3 and
install it as ``lie_learn==0.0.2+np2`` (which still satisfies escnn's pin).
Nothing is downloaded outside the package registry.

Usage: python scripts/build_lie_learn.py CACHE_DIR   (prints the built wheel's path; a
lie_learn-0.0.2 wheel already in CACHE_DIR is used instead of downloading one)
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

VERSION = "0.0.2+np2"

SETUP_PY = """
import numpy
from Cython.Build import cythonize
from setuptools import Extension, find_packages, setup

pyx = {pyx!r}
extensions = [
    Extension(p[:-4].replace("/", "."), [p], include_dirs=[numpy.get_include()])
    for p in pyx
]
setup(
    name="lie_learn",
    version="{version}",
    packages=find_packages(),
    package_data={{"": ["*.npy"]}},
    install_requires=["numpy>=2", "scipy", "requests"],
    ext_modules=cythonize(
        extensions,
        compiler_directives={{"language_level": 2, "legacy_implicit_noexcept": True}},
    ),
)
"""

SCIPY_COMPAT = '''"""scipy.special.sph_harm was removed in SciPy 1.17; sph_harm_y swaps the argument order."""
try:
    from scipy.special import sph_harm_y as _sph_harm_y

    def sph_harm(m, n, theta, phi):
        return _sph_harm_y(n, m, phi, theta)
except ImportError:  # older SciPy
    from scipy.special import sph_harm  # noqa: F401
'''


def patch_source(text: str) -> str:
    # numpy 2's Cython declarations dropped the aliased *_t types as well.
    text = re.sub(r"\bnp\.int_t\b", "np.int64_t", text)
    text = re.sub(r"\bnp\.float_t\b", "np.float64_t", text)
    text = re.sub(r"\bnp\.complex_t\b", "np.complex128_t", text)
    text = re.sub(r"\bnp\.int\b(?!\w)", "np.int64", text)
    text = re.sub(r"\bnp\.float\b(?!\w)", "np.float64", text)
    text = re.sub(r"\bnp\.complex\b(?!\w)", "np.complex128", text)
    text = text.replace("collections.Iterable", "collections.abc.Iterable")
    text = text.replace(
        "from numpy.lib.index_tricks import as_strided",
        "from numpy.lib.stride_tricks import as_strided",
    )

    def fix_import(match: re.Match) -> str:
        indent, names = match.group(1), [n.strip() for n in match.group(2).split(",")]
        rest = [n for n in names if n != "sph_harm"]
        lines = [f"{indent}from lie_learn._scipy_compat import sph_harm"]
        if rest:
            lines.insert(0, f"{indent}from scipy.special import {', '.join(rest)}")
        return "\n".join(lines)

    return re.sub(
        r"^([ \t]*)from scipy\.special import ([^\n]*\bsph_harm\b[^\n]*)$", fix_import, text, flags=re.MULTILINE
    )


def build(cache: Path) -> Path:
    cache.mkdir(parents=True, exist_ok=True)
    built = sorted(cache.glob("lie_learn-0.0.2+np2-*.whl"))
    if built:
        return built[-1]
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        # The registry's wheel, or one already placed in CACHE_DIR (machines without a registry).
        wheel = next(iter(sorted(cache.glob("lie_learn-0.0.2-*.whl"))), None)
        if wheel is None:
            subprocess.run(
                [
                    sys.executable,
                    "-m",
                    "pip",
                    "download",
                    "--no-deps",
                    "--only-binary=:all:",
                    "lie_learn==0.0.2",
                    "-d",
                    str(tmp / "dl"),
                    "-q",
                ],
                check=True,
            )
            wheel = next((tmp / "dl").glob("lie_learn-0.0.2-*.whl"))
        src = tmp / "src"
        with zipfile.ZipFile(wheel) as zf:
            zf.extractall(src)
        for stale in [*src.glob("*.dist-info"), *src.glob("*.libs")]:
            shutil.rmtree(stale)
        for stale in [*src.rglob("*.so"), *src.rglob("*.c")]:
            stale.unlink()
        for source in [*src.rglob("*.py"), *src.rglob("*.pyx")]:
            source.write_text(patch_source(source.read_text()))
        (src / "lie_learn" / "_scipy_compat.py").write_text(SCIPY_COMPAT)
        for pkg_dir in (src / "lie_learn").rglob("*"):
            if pkg_dir.is_dir() and not (pkg_dir / "__init__.py").exists() and not pkg_dir.name.startswith("__"):
                (pkg_dir / "__init__.py").write_text("")
        pyx = sorted(str(p.relative_to(src)) for p in src.rglob("*.pyx"))
        (src / "setup.py").write_text(SETUP_PY.format(pyx=pyx, version=VERSION))
        subprocess.run(
            [
                sys.executable,
                "-m",
                "pip",
                "wheel",
                "--no-deps",
                "--no-build-isolation",
                "-w",
                str(cache),
                str(src),
                "-q",
            ],
            check=True,
        )
    return next(cache.glob("lie_learn-0.0.2+np2-*.whl"))


if __name__ == "__main__":
    print(build(Path(sys.argv[1]).resolve()))
