"""Python dependencies of the add-on: where they live, whether they import, how to install them.

torch is far too large to bundle, so the add-on never imports it at registration time.  It is looked
up, in this order, in:

1. folders listed in the environment variable ``NEUMESH_PYTHONPATH`` (``os.pathsep`` separated),
2. the "Existing environment" folder of the add-on preferences (a ``site-packages`` directory),
3. the add-on's own dependency folder, filled by "Install dependencies" (pip with Blender's Python).

Each is put at the *front* of ``sys.path`` so the pinned versions win over anything else on the path.
Nothing in this module needs bpy except :func:`addon_deps_dir` (which asks Blender for a user folder).
"""
from __future__ import annotations

import importlib
import importlib.metadata
import importlib.util
import os
import sys

ENV_VAR = "NEUMESH_PYTHONPATH"

# The add-on's Python dependencies, one list for the add-on's *Install dependencies* and for
# scripts/setup_blender.sh (which reads it with runpy: keep this module free of relative imports).
# (import name, distribution name, required, pip requirement, features that need it)
# numpy's requirement is chosen per Blender (see numpy_requirement), never installed over Blender's own.
DEPENDENCIES = (
    ("torch", "torch", True, "torch==2.13.0", ()),
    ("numpy", "numpy", True, "numpy", ()),
    ("safetensors", "safetensors", True, "safetensors", ()),
    ("PIL", "pillow", True, "pillow", ()),
    ("scipy", "scipy", False, "scipy", ("scaffold", "semantics", "select", "edit", "bake_field")),
    ("pykdtree", "pykdtree", False, "pykdtree", ("select", "edit")),
    ("trimesh", "trimesh", False, "trimesh", ()),
    ("sklearn", "scikit-learn", False, "scikit-learn", ("semantics", "select")),   # PCA, DBSCAN
    # superpixels, marching cubes
    ("skimage", "scikit-image", False, "scikit-image", ("semantics", "scaffold", "bake_field")),
    # the field-surface bake's decimation (the core falls back to libigl's collapse)
    ("fast_simplification", "fast-simplification", False, "fast-simplification", ("bake_field",)),
    ("xatlas", "xatlas", False, "xatlas", ("bake",)),                              # UV atlas
    ("pycolmap", "pycolmap", False, "pycolmap>=4", ("capture",)),                   # COLMAP folders, poses from photos
    ("cv2", "opencv-python-headless", False, "opencv-python-headless<4.12", ("capture",)),  # undistortion, video
    # shape-aware selection: the scaffold's Laplacian; without it selection uses colour alone
    ("robust_laplacian", "robust-laplacian", False, "robust-laplacian", ("shape",)),
)
FEATURES = {"scaffold": "Build scaffold", "semantics": "Distill semantics", "select": "Select by click",
            "edit": "Texture edits", "bake": "Bake to material", "capture": "Real captures (COLMAP, video)",
            "shape": "Shape-aware selection", "bake_field": "Bake onto the field surface"}


def numpy_requirement(blender_version=None) -> str:
    """numpy for a Blender that has none: 1.26 (numpy<2) for Blender 3.4-4.x, numpy 2 for Blender 5+."""
    if blender_version is None:
        try:
            import bpy

            blender_version = tuple(bpy.app.version)
        except Exception:  # noqa: BLE001 - outside Blender
            blender_version = (4, 0, 0)
    return "numpy>=2" if tuple(blender_version) >= (5, 0, 0) else "numpy<2"


def requirement(name: str, blender_version=None) -> str:
    """The pip requirement of dependency ``name`` (import name or distribution name)."""
    for imp, dist, _req, pip_req, _f in DEPENDENCIES:
        if name in (imp, dist):
            return numpy_requirement(blender_version) if imp == "numpy" else pip_req
    raise KeyError(name)


def full_requirements(blender_version=None) -> list[str]:
    """Every dependency's pip requirement: what a fresh folder for a Blender without numpy needs
    (scripts/setup_blender.sh installs this for Debian's Blender 3.4)."""
    return [requirement(d[0], blender_version) for d in DEPENDENCIES]


PIP_REQUIREMENTS = tuple(full_requirements((4, 0, 0)))

_added_paths: list[str] = []


def python_tag() -> str:
    return "py%d%d" % sys.version_info[:2]


def addon_deps_dir(package: str | None = None, create: bool = False) -> str:
    """Folder the add-on owns for pip-installed packages (per Python version)."""
    import bpy

    package = package or __package__
    base = None
    fn = getattr(bpy.utils, "extension_path_user", None)
    if fn is not None and package and package.startswith("bl_ext."):
        try:
            base = fn(package, path="", create=create)
        except Exception:  # not an extension (legacy install) or no writable user dir
            base = None
    if not base:
        base = bpy.utils.user_resource("SCRIPTS", path=os.path.join("addons_data", "neumesh"), create=create)
    path = os.path.join(base, "site-packages-" + python_tag())
    if create:
        os.makedirs(path, exist_ok=True)
    return path


def env_paths() -> list[str]:
    raw = os.environ.get(ENV_VAR, "")
    return [p for p in raw.split(os.pathsep) if p.strip()]


def configure_sys_path(extra: list[str] | tuple[str, ...] = ()) -> list[str]:
    """Put the dependency folders at the front of sys.path (idempotent). Returns the folders used.

    Folders that do not exist are skipped. Previously added folders that are no longer wanted
    (e.g. the preference changed) are removed again.
    """
    wanted: list[str] = []
    for p in list(env_paths()) + [e for e in extra if e]:
        p = os.path.abspath(os.path.expanduser(p))
        if os.path.isdir(p) and p not in wanted:
            wanted.append(p)
    for p in list(_added_paths):
        if p not in wanted and p in sys.path:
            sys.path.remove(p)
        if p not in wanted:
            _added_paths.remove(p)
    for p in reversed(wanted):
        if p in sys.path:
            sys.path.remove(p)
        sys.path.insert(0, p)
        if p not in _added_paths:
            _added_paths.append(p)
    importlib.invalidate_caches()
    return wanted


class DepStatus:
    __slots__ = ("name", "dist", "required", "found", "version", "location", "error")

    def __init__(self, name, dist, required):
        self.name, self.dist, self.required = name, dist, required
        self.found = False
        self.version = ""
        self.location = ""
        self.error = ""

    def __repr__(self):
        return f"DepStatus({self.name!r}, found={self.found}, version={self.version!r}, error={self.error!r})"


def check_dependencies(do_import: bool = False) -> list[DepStatus]:
    """Status of every dependency.

    do_import=False only locates the module and reads its installed version (cheap, safe in draw()).
    do_import=True really imports it (catches broken installs, e.g. an ABI mismatch).
    """
    importlib.invalidate_caches()
    out = []
    for name, dist, required, _req, _features in DEPENDENCIES:
        st = DepStatus(name, dist, required)
        try:
            mod = sys.modules.get(name)
            spec = None if mod is not None else importlib.util.find_spec(name)
            if mod is None and spec is None:
                st.error = "not found"
                out.append(st)
                continue
            st.location = os.path.dirname(getattr(mod, "__file__", None) or (spec.origin if spec else "") or "")
            if do_import and mod is None:
                mod = importlib.import_module(name)
            ver = getattr(mod, "__version__", None) if mod is not None else None
            if not ver:
                try:
                    ver = importlib.metadata.version(dist)
                except Exception:
                    ver = "?"
            st.version = str(ver)
            st.found = True
        except Exception as exc:  # broken install: report, never raise into the UI
            st.found = False
            st.error = f"{type(exc).__name__}: {exc}"
        out.append(st)
    return out


def missing_required(statuses=None) -> list[str]:
    statuses = statuses if statuses is not None else check_dependencies()
    return [s.dist for s in statuses if s.required and not s.found]


def missing_for(feature: str, statuses=None) -> list[str]:
    """Distribution names (as pip knows them) that ``feature`` (a key of FEATURES) needs and Blender's
    Python cannot find."""
    need = [d for d in DEPENDENCIES if feature in d[4]]
    if statuses is not None:
        found = {s.dist for s in statuses if s.found}
        return [d[1] for d in need if d[1] not in found]
    out = []   # cheap enough for a panel's draw(): no cache invalidation, nothing imported
    for imp, dist, *_ in need:
        if imp in sys.modules:
            continue
        try:
            ok = importlib.util.find_spec(imp) is not None
        except (ImportError, ValueError):
            ok = False
        if not ok:
            out.append(dist)
    return out


def missing_message(feature: str, missing: list[str]) -> str:
    """What to tell the artist when ``feature`` cannot start for want of ``missing``."""
    what = FEATURES.get(feature, feature)
    pkgs = ", ".join(missing)
    it = "them" if len(missing) > 1 else "it"
    return (f"{what} needs the Python package{'s' if len(missing) > 1 else ''} {pkgs}, which Blender's Python "
            f"cannot import. Install {it} with the button in the NeuMesh panel ('{install_label(missing)}'), with "
            f"Install dependencies in Edit > Preferences > Add-ons > NeuMesh, or add {it} to the 'Existing "
            "environment' folder")


def install_label(missing: list[str]) -> str:
    """The text of the button that installs ``missing`` (short enough for the sidebar)."""
    return f"Install {missing[0]}" if len(missing) == 1 else f"Install these {len(missing)}"


def own_numpy_version(statuses=None) -> str | None:
    """The version of the numpy that Blender's Python has by itself (outside the folders this module
    put on sys.path), or None when it has none."""
    import importlib.machinery

    own = {os.path.abspath(p) for p in _added_paths}
    paths = [p for p in sys.path if p and os.path.abspath(p) not in own]
    spec = importlib.machinery.PathFinder.find_spec("numpy", paths)
    if spec is None or not spec.origin:
        return None
    site = os.path.dirname(os.path.dirname(spec.origin))
    for d in importlib.metadata.distributions(path=[site]):
        if (d.metadata["Name"] or "").lower() == "numpy":
            return d.version
    return "unknown"


def install_plan(wanted=None, statuses=None, blender_version=None, blender_numpy="auto"):
    """(requirements, keep_out): what *Install dependencies* asks pip for and the distributions to take
    out of the target folder afterwards.

    Only what the running Blender lacks is installed (``wanted``: distribution/import names to consider,
    default all). numpy is never installed over a Blender that ships one: pip's ``--target`` installs every
    dependency of what it installs, so Blender's numpy version is pinned (the other packages are resolved
    against it) and numpy is removed from the folder afterwards (a copy there would shadow Blender's)."""
    statuses = statuses if statuses is not None else check_dependencies()
    found = {s.dist for s in statuses if s.found}
    if blender_numpy == "auto":
        blender_numpy = own_numpy_version()
    names = [d for d in DEPENDENCIES if wanted is None or d[0] in wanted or d[1] in wanted]
    reqs = [requirement(d[0], blender_version) for d in names
            if d[1] not in found and not (d[0] == "numpy" and blender_numpy)]
    keep_out = []
    if blender_numpy and reqs:
        if blender_numpy != "unknown":
            reqs.append(f"numpy=={blender_numpy}")
        keep_out.append("numpy")
    return reqs, keep_out
