"""Build the documentation: ``python docs/build.py [--out docs/_build]``.

Writes ``index.md`` (the user guide), ``api.md`` (API reference generated from the
docstrings of every public module, class and function) and copies the figures of
``results/*/`` that exist into ``figures/``.  Fails (exit 1) when a public object has
no docstring, so the reference cannot silently rot; the test suite runs it.
"""
from __future__ import annotations

import argparse
import importlib
import inspect
import pkgutil
import shutil
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent

SKIP_MODULES = ("avsm_dr.__main__",)


def public_modules():
    import avsm_dr
    yield avsm_dr
    for info in pkgutil.walk_packages(avsm_dr.__path__, "avsm_dr."):
        name = info.name
        if any(part.startswith("_") for part in name.split(".")[1:]) or name in SKIP_MODULES:
            continue
        yield importlib.import_module(name)


def _members(module):
    for name, obj in sorted(vars(module).items()):
        if name.startswith("_"):
            continue
        if (inspect.isfunction(obj) or inspect.isclass(obj)) and getattr(obj, "__module__", None) == module.__name__:
            yield name, obj


def _signature(obj):
    try:
        return str(inspect.signature(obj))
    except (TypeError, ValueError):
        return "(...)"


def api_markdown() -> tuple[str, list[str]]:
    lines = ["# API reference", "", "Generated from the docstrings by `python docs/build.py`.", ""]
    missing = []
    for module in public_modules():
        doc = inspect.getdoc(module)
        if not doc:
            missing.append(module.__name__)
        lines += [f"## `{module.__name__}`", "", doc or "", ""]
        for name, obj in _members(module):
            qual = f"{module.__name__}.{name}"
            odoc = inspect.getdoc(obj)
            if not odoc:
                missing.append(qual)
            kind = "class" if inspect.isclass(obj) else "def"
            lines += [f"### {kind} `{name}{_signature(obj)}`", "", odoc or "*(no docstring)*", ""]
            if inspect.isclass(obj):
                for mname, meth in sorted(vars(obj).items()):
                    if mname.startswith("_") or not (inspect.isfunction(meth) or isinstance(meth, property)):
                        continue
                    mdoc = inspect.getdoc(meth)
                    if not mdoc:
                        continue  # documented by the base class contract
                    sig = "" if isinstance(meth, property) else _signature(meth)
                    lines += [f"#### `{name}.{mname}{sig}`", "", mdoc, ""]
    return "\n".join(lines), missing


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=str(HERE / "_build"))
    parser.add_argument("--results", default=str(ROOT / "results"))
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    shutil.copy(HERE / "guide.md", out / "index.md")
    api, missing = api_markdown()
    (out / "api.md").write_text(api)
    figures = out / "figures"
    figures.mkdir(exist_ok=True)
    copied = 0
    for png in sorted(Path(args.results).glob("*/*.png")):
        shutil.copy(png, figures / f"{png.parent.name}__{png.name}")
        copied += 1
    print(f"docs: wrote {out / 'index.md'}, {out / 'api.md'} ({api.count('### ')} entries), {copied} figures")
    if missing:
        print("docs: missing docstrings:\n  " + "\n  ".join(missing), file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
