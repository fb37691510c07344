"""The ground floor by concept: the old module paths warn for a release, nothing in the repository
imports them, the modules of localscale import each other in no loop, and files and functions stay
short."""

import ast
import importlib
import sys
import warnings
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: old module -> (new module, a few of its names)
MOVED = {
    "localscale.planar": ("localscale.geometry.planar", ("planarize",)),
    "localscale.cameras": ("localscale.geometry.cameras", ("Camera", "CameraError", "as_camera", "read_camera")),
    "localscale.camera_checks": ("localscale.geometry.camera_checks", ("check_plausible", "implausibility")),
    "localscale.two_view": ("localscale.geometry.two_view", ("TwoViewConfig", "estimate_two_view_geometry")),
    "localscale.relative_pose": ("localscale.geometry.relative_pose", ("relative_pose_error", "pose_auc")),
    "localscale.anchoring": ("localscale.models.anchoring", ("anchored_prediction",)),
    "localscale.errors": ("localscale.core.errors", ("LocalScaleError", "ImageError", "OutputError")),
    "localscale.outputs": ("localscale.core.outputs", ("atomic_path", "write_text")),
    "localscale.devices": ("localscale.core.devices", ("resolve_device",)),
    "localscale.checks": ("localscale.core.checks", ("check_int",)),
    "localscale.lazy": ("localscale.core.lazy", ("lazy_exports",)),
    "localscale.image_files": ("localscale.io.image_files", ("read_header",)),
    "localscale.preprocess": ("localscale.io.preprocess", ("Letterbox", "letterbox")),
    "localscale.pairs_file": ("localscale.io.pairs_file", ("PairsFileError", "read_pairs_file")),
    "localscale.map_files": ("localscale.maps.files", ("write_scale_map", "write_refinement")),
}


@pytest.mark.parametrize("old", sorted(MOVED))
def test_an_old_module_warns_and_gives_the_new_modules_names(old):
    new, names = MOVED[old]
    sys.modules.pop(old, None)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        module = importlib.import_module(old)
    messages = [str(w.message) for w in caught if issubclass(w.category, DeprecationWarning)]
    assert any(new in m and "next release" in m for m in messages), messages
    target = importlib.import_module(new)
    for name in names:
        assert getattr(module, name) is getattr(target, name)


def test_the_geometry_package_keeps_the_homography_names():
    import localscale.geometry as geometry
    from localscale.geometry import homography

    for name in (
        "project",
        "turn_matrix",
        "homography_scale_map",
        "sample_homography",
        "warp_image",
        "HomographyConfig",
    ):
        assert getattr(geometry, name) is getattr(homography, name)


def test_the_io_package_keeps_the_image_names():
    import localscale.io as io
    from localscale.io import images

    for name in ("load_image", "read_homography", "image_shape", "load_working_image", "ImageLike", "MAX_PIXELS"):
        assert getattr(io, name) is getattr(images, name)


def _modules(folder: Path) -> dict:
    """``{dotted name: path}`` of the Python files under ``folder`` (a package of the repository)."""
    out = {}
    for path in folder.rglob("*.py"):
        parts = list(path.relative_to(ROOT).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def _imports(name: str, path: Path) -> set:
    """Every module name an import statement of ``path`` (module ``name``) names, lazy ones too:
    ``from a import b`` names ``a`` and ``a.b``."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            found.add(module)
            found.update(f"{module}.{a.name}" for a in node.names)
    return found


def test_nothing_in_the_repository_imports_an_old_path():
    shims = set(MOVED) | {f"localscale.{m}" for m in ("matching.hypotheses", "matching.localization", "matching.turns")}
    offenders = []
    for folder in ("localscale", "tests", "eval", "train", "examples"):
        for name, path in _modules(ROOT / folder).items():
            if name in shims:
                continue
            used = _imports(name, path) & shims
            offenders += [f"{path.relative_to(ROOT)} imports {m}" for m in sorted(used)]
    assert not offenders, offenders


def _loops(graph: dict) -> list:
    """The strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on_stack, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                out.append(sorted(component))

    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10_000))
    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_the_modules_of_localscale_import_each_other_in_no_loop():
    """Module A -> module B when A imports B (at the top or inside a function); package faces
    (``__init__.py``) are left out, as importing one of their modules does not go through them."""
    modules = {n: p for n, p in _modules(ROOT / "localscale").items() if p.name != "__init__.py"}
    graph = {n: sorted(m for m in _imports(n, p) if m in modules and m != n) for n, p in modules.items()}
    assert _loops(graph) == []


def test_no_file_over_600_lines_and_no_function_over_80():
    long_files, long_functions = [], []
    for path in sorted((ROOT / "localscale").rglob("*.py")):
        text = path.read_text(encoding="utf-8")
        if text.count("\n") > 600:
            long_files.append(str(path.relative_to(ROOT)))
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node.end_lineno - node.lineno + 1 > 80:
                long_functions.append(f"{path.relative_to(ROOT)}:{node.name}")
    assert not long_files and not long_functions, (long_files, long_functions)


def test_pairs_txt_is_read_by_the_one_pairs_parser(tmp_path):
    from localscale.io.pairs_file import PairsFileError
    from localscale.sfm.pairs import read_pairs, write_pairs

    pairs = [("my photo.jpg", "b #2.png"), ("it's.jpg", "plain.jpg"), ("sub/dir/x.JPG", 'quote".png')]
    write_pairs(tmp_path / "pairs.txt", pairs)
    assert read_pairs(tmp_path / "pairs.txt") == pairs
    (tmp_path / "bad.txt").write_text("a.jpg b.jpg c.jpg\n")
    with pytest.raises(PairsFileError, match=":1: expected two images"):
        read_pairs(tmp_path / "bad.txt")


def test_one_markdown_table_and_the_evaluations_old_name_warns():
    from localscale.core.tables import markdown_table
    from localscale.evaluation import report

    assert markdown_table([{"a": 1.23456, "b": None}], [("a", "A"), ("b", "B")]).splitlines()[-1] == "| 1.23 | - |"
    with pytest.warns(DeprecationWarning, match="matching_table"):
        assert report.markdown_table is report.matching_table
