"""The spec file (SPEC section 1): YAML -> frozen Spec dataclasses.

Every mistake in a spec is collected first and raised once, as one SpecError whose `problems` are each
`key.path: what is wrong (got X, expected Y)`, so a user fixes a spec in one round instead of many.
Only checks that need nothing but the spec itself (and the existence of the files it names) live here;
checks that need the model's geometry (pin too wide for its face, periodic faces that do not meet, grid
finer than the tolerance allows) belong to the later stages.

The YAML is read with `yaml.safe_load` only: a `!!python/...` tag never constructs anything.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import re
import reprlib
import stat
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from .errors import SpecError
from .grid import AXES as _GRID_AXES
from .limits import LIMIT_HELP, Limits

__all__ = [
    "AXES", "UNIT_SCALE", "MESH_SUFFIXES", "NURBS_SUFFIXES", "CAGE_TYPES",
    "ModelSpec", "CageSpec", "ShellSpec", "TextureSpec", "RandomizeSpec", "JointSpec", "OutputSpec", "Spec",
    "load_spec", "load_spec_text", "with_overrides", "spec_to_dict",
]

# a tuple, not the string: `name in AXES` must not accept "uv" or ""
AXES = tuple(_GRID_AXES)
UNIT_SCALE = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "in": 25.4}  # mm per model unit
MESH_SUFFIXES = (".stl", ".obj", ".ply", ".off", ".3mf", ".glb")
NURBS_SUFFIXES = (".json", ".xml", ".itd")
SURFACE_SUFFIXES = (".nurbs", ".json", ".xml", ".itd")
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")
TEXTURE_FACES = ("u_min", "u_max", "v_min", "v_max", "w_min", "w_max")
CAGE_TYPES = ("box", "cylinder", "sphere")
JOINT_STYLES = ("pin", "dowel", "none")
JOINT_ALLOW = ("loose", "welded")
JOINT_SHAPES = ("cylinder", "snap")
JOINT_SPACES = ("physical", "domain")
FORMATS = ("stl", "3mf")
SPLIT_MODES = ("uniform", "knots", "balanced")

DEFAULT_CAGE_PADDING = 1.0  # mm: keeps the mesh off the cage boundary, where Booleans would be coplanar
_NAME_RE = re.compile(r"[A-Za-z0-9_-]+")
_YAML11_FLOAT = re.compile(r"[-+]?[0-9]+(\.[0-9]*)?[eE][-+]?[0-9]+")
_MAX_CLEARANCE = 2.0  # mm: print clearances are tenths of a millimetre; more leaves the pin loose in its hole
_NAME_MAX = 100

_TOP_KEYS = ("name", "model", "grid", "splits", "periodic", "randomize", "joints", "output", "texture",
             "limits")
_MODEL_KEYS = ("nurbs", "patch", "builtin", "mesh", "shell", "cage", "units", "size", "repair")
_SHELL_KEYS = ("surface", "thickness", "patch", "side")
_SHELL_SIDES = ("inward", "outward", "both")
_TEXTURE_KEYS = ("image", "face", "transpose")
_CAGE_KEYS = ("type", "padding", "control_points", "nurbs", "patch")
_RANDOMIZE_KEYS = ("seed", "amplitude", "control_points")
_JOINT_KEYS = ("style", "shape", "radius", "length", "clearance", "axial_clearance", "space", "min_radius",
               "min_length", "allow")
_OUTPUT_KEYS = ("directory", "format", "tolerance", "plate", "spacing", "labels", "margin", "face_clearance")


# ----------------------------------------------------------------------------------------------------
# The data


@dataclass(frozen=True)
class CageSpec:
    """The cage around a mesh: a simple shape (`type` box|cylinder|sphere) or a NURBS file (`type` nurbs).

    padding is in mm of the printed object; control_points None lets the cage builder choose.
    """
    type: str
    nurbs: Path | None = None
    patch: int = 0
    padding: float = DEFAULT_CAGE_PADDING
    control_points: tuple[int, int, int] | None = None


@dataclass(frozen=True)
class ShellSpec:
    """A thick shell round a NURBS surface: thickness in mm of the printed (sized) object; side: inward, outward,
    both (half each way) or the share (0..1) of the wall outside the surface."""
    surface: Path
    thickness: float
    patch: int = 0
    side: str | float = "inward"


@dataclass(frozen=True)
class TextureSpec:
    """An image on one boundary face of the model, through the two other parameters: image rows follow the first
    of them (top = its minimum), columns the second (left = its minimum); transpose swaps that."""
    image: Path
    face: str = "w_max"
    transpose: bool = False


@dataclass(frozen=True)
class ModelSpec:
    """Exactly one of nurbs / builtin / mesh / shell is set. unit_scale is mm per model unit."""
    nurbs: Path | None = None
    patch: int = 0
    builtin: dict | None = None
    mesh: Path | None = None
    shell: ShellSpec | None = None
    cage: CageSpec | None = None
    units: str = "mm"
    unit_scale: float = 1.0
    size: float | None = None
    repair: bool = False


@dataclass(frozen=True)
class RandomizeSpec:
    seed: int = 0
    amplitude: float = 0.25
    control_points: int = 6


@dataclass(frozen=True)
class JointSpec:
    """radius / length None: derived from the cell sizes by the joint stage."""
    style: str = "pin"
    shape: str = "cylinder"
    radius: float | None = None
    length: float | None = None
    clearance: float = 0.15
    axial_clearance: float = 0.3
    space: str = "physical"
    min_radius: float = 1.0
    min_length: float = 3.0
    allow: tuple = ()  # of JOINT_ALLOW: pieces without a joint ("loose") or that cannot come out ("welded")


@dataclass(frozen=True)
class OutputSpec:
    """directory is absolute (resolved); None only before a name is known."""
    directory: Path | None = None
    format: str = "stl"
    tolerance: float = 0.05
    plate: tuple[float, float] = (250.0, 210.0)
    spacing: float = 4.0
    labels: bool = True
    margin: float = 10.0  # bed edge to the nearest piece, mm: room for the slicer's skirt
    face_clearance: float = 0.15  # gap between mating cut faces, mm; each face is set back by half of it


@dataclass(frozen=True)
class Spec:
    """A checked spec. splits[k] is 'uniform' | 'knots' | tuple of grid[k]-1 increasing parameters;
    periodic holds axis indices (0, 1, 2), sorted; randomize is None when absent or amplitude 0."""
    name: str
    model: ModelSpec
    grid: tuple[int, int, int]
    splits: tuple = ("uniform", "uniform", "uniform")
    periodic: tuple[int, ...] = ()
    randomize: RandomizeSpec | None = None
    joints: JointSpec = field(default_factory=JointSpec)
    output: OutputSpec = field(default_factory=OutputSpec)
    limits: Limits = field(default_factory=Limits)
    texture: TextureSpec | None = None
    source: Path | None = None
    raw: dict = field(default_factory=dict, compare=False, repr=False)


# ----------------------------------------------------------------------------------------------------
# Showing values in messages

_repr = reprlib.Repr()
_repr.maxstring = 60
_repr.maxother = 60
_repr.maxlist = 6
_repr.maxdict = 4
_repr.maxlevel = 3


def _kind(value) -> str:
    if value is None:
        return "nothing"
    if isinstance(value, bool):
        return "a boolean"
    if isinstance(value, int):
        return "an integer"
    if isinstance(value, float):
        return "a number"
    if isinstance(value, str):
        return "a text"
    if isinstance(value, list):
        return "a list"
    if isinstance(value, dict):
        return "a mapping"
    return f"a {type(value).__name__}"


def _show(value) -> str:
    """A short, YAML-flavoured rendering of a value a user wrote."""
    if value is None:
        return "nothing"
    if isinstance(value, bool):
        # YAML 1.1 reads yes/no/on/off as booleans, which surprises people: say so
        return f"{'true' if value else 'false'} (a boolean; YAML reads yes/no/on/off as booleans)"
    if isinstance(value, (int, float, str)):
        return _repr.repr(value)
    if isinstance(value, (list, dict)):
        return f"{_kind(value)} {_repr.repr(value)}"
    return f"{_repr.repr(value)} ({_kind(value)})"


def _num(x: float) -> str:
    return f"{x:g}"


def _one_of(options) -> str:
    return "one of: " + ", ".join(str(o) for o in options)


def _suggest(word, options) -> str:
    """', did you mean 'x'?' for the nearest option, or ''."""
    if not isinstance(word, str):
        return ""
    low = {str(o).lower(): o for o in options}
    hits = difflib.get_close_matches(word.lower(), list(low), n=1, cutoff=0.6)
    return f", did you mean '{low[hits[0]]}'?" if hits else ""


def _path_join(parent: str, key) -> str:
    """parent.key, or parent[i] for a list index; odd keys (spaces, dots, empty) are quoted."""
    if isinstance(key, int) and not isinstance(key, bool):
        return f"{parent}[{key}]"
    key = key if isinstance(key, str) and _NAME_RE.fullmatch(key) else _repr.repr(key)
    return f"{parent}.{key}" if parent else key


# ----------------------------------------------------------------------------------------------------
# The checker: each method returns a cleaned value or None, and records what is wrong


class _Checker:
    def __init__(self, base: Path):
        self.base = base
        self.problems: list[str] = []

    def bad(self, path: str, what: str, got: str, expected: str) -> None:
        self.problems.append(f"{path}: {what} (got {got}, expected {expected})")

    # ---- structure

    def mapping(self, path, value, keys, *, allow_none=True):
        """The value as a dict with only known keys (unknown ones reported); None if it is not a mapping."""
        if value is None and allow_none:
            return {}
        if not isinstance(value, dict):
            self.bad(path, "not a mapping", _show(value), f"a mapping with keys {_one_of(keys)[8:]}")
            return None
        out = {}
        for key, item in value.items():
            if isinstance(key, str) and key in keys:
                out[key] = item
                continue
            self.bad(_path_join(path, key if isinstance(key, str) else str(key)),
                     "unknown key" + _suggest(key, keys), _show(key), _one_of(keys))
        return out

    # ---- scalars

    def integer(self, path, value, minimum=None, what="an integer"):
        expected = what if minimum is None else f"{what} >= {minimum}"
        if isinstance(value, bool):
            self.bad(path, "a boolean where an integer belongs", _show(value), expected)
            return None
        if isinstance(value, float) and math.isfinite(value) and value == int(value):
            self.bad(path, "a decimal number where an integer belongs", _show(value),
                     f"{expected}, written without a decimal point ({int(value)})")
            return None
        if not isinstance(value, int):
            self.bad(path, "not an integer", _show(value), expected)
            return None
        if minimum is not None and value < minimum:
            self.bad(path, "too small", _show(value), expected)
            return None
        return value

    def number(self, path, value, *, above=None, at_least=None, allow_none=False, at_most=None, why=""):
        if at_least is not None:
            expected = f"a number >= {_num(at_least)}"
        elif above is not None:
            expected = f"a number > {_num(above)}"
        else:
            expected = "a number"
        if allow_none:
            expected += ", or nothing for the default"
        if value is None and allow_none:
            return None
        if isinstance(value, str) and _YAML11_FLOAT.fullmatch(value.strip()):
            # YAML 1.1 reads 1e-6 (no decimal point) as a text; it is a number in every other reading
            value = float(value)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            self.bad(path, "not a number", _show(value), expected)
            return None
        if not math.isfinite(value):
            self.bad(path, "not a finite number", _show(value), expected)
            return None
        if (at_least is not None and value < at_least) or (above is not None and value <= above):
            self.bad(path, "out of range", _show(value), expected)
            return None
        if at_most is not None and value > at_most:
            self.bad(path, "too large", _show(value), f"{expected} and <= {_num(at_most)}{why}")
            return None
        return float(value)

    def boolean(self, path, value):
        if not isinstance(value, bool):
            self.bad(path, "not a boolean", _show(value), "true or false")
            return None
        return value

    def enum(self, path, value, options):
        if isinstance(value, str) and value.strip().lower() in options:
            return value.strip().lower()
        if isinstance(value, str):
            self.bad(path, "unknown value" + _suggest(value, options), _show(value), _one_of(options))
        else:
            self.bad(path, "not one of the accepted values", _show(value), _one_of(options))
        return None

    def file(self, path, value, suffixes, what):
        """A path to an existing file, relative to the spec's folder; the resolved Path or None."""
        if not isinstance(value, str) or not value.strip():
            self.bad(path, "not a file path", _show(value), f"the path of {what}, relative to the spec's folder")
            return None
        try:
            resolved = (self.base / Path(value.strip()).expanduser()).resolve()
        except (OSError, RuntimeError, ValueError) as exc:
            self.bad(path, f"cannot be resolved ({exc})", _show(value), f"the path of {what}")
            return None
        if resolved.suffix.lower() not in suffixes:
            self.bad(path, "unsupported file type", _show(value),
                     f"{what} ending in {_one_of(suffixes)[8:]}")
            return None
        try:
            st = resolved.stat()
        except FileNotFoundError:
            st = None
        except (OSError, ValueError) as exc:
            self.bad(path, f"cannot be opened ({getattr(exc, 'strerror', None) or exc})", _show(value),
                     f"the path of {what}")
            return None
        if st is not None and stat.S_ISDIR(st.st_mode):
            self.bad(path, "is a folder, not a file", repr(str(resolved)), f"{what} file")
            return None
        if st is not None and not stat.S_ISREG(st.st_mode):
            kind = "a FIFO (named pipe)" if stat.S_ISFIFO(st.st_mode) else "a device or socket"
            self.bad(path, f"is {kind}, not a regular file", repr(str(resolved)), f"{what} as a regular file")
            return None
        if st is None:
            self.bad(path, "file not found", repr(str(resolved)),
                     f"an existing file; relative paths are read from the spec's folder {self.base}")
            return None
        return resolved

    # ---- sections

    def name(self, value):
        expected = f"letters, digits, '-' and '_' only (at most {_NAME_MAX}), as it names the output folder"
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            self.bad("name", "not a text", _show(value), expected + f"; quote it: \"{value}\"")
            return None
        if not isinstance(value, str) or not value:
            self.bad("name", "not a text", _show(value), expected)
            return None
        if not _NAME_RE.fullmatch(value) or len(value) > _NAME_MAX:
            what = ("not a plain file name" if any(c in value for c in "/\\.:") or value in (".", "..")
                    else "contains characters a name cannot have")
            self.bad("name", what, _show(value), expected)
            return None
        return value

    def model(self, value):
        m = self.mapping("model", value, _MODEL_KEYS, allow_none=False)
        if m is None:
            return None
        sources = [k for k in ("nurbs", "builtin", "mesh", "shell") if k in m]
        if len(sources) != 1:
            got = " and ".join(sources) if sources else "none of them"
            self.bad("model", "more than one model source" if sources else "no model source", got,
                     "exactly one of nurbs, builtin, mesh, shell")
        kind = sources[0] if len(sources) == 1 else None

        nurbs = self.file("model.nurbs", m["nurbs"], NURBS_SUFFIXES, "a NURBS volume") if "nurbs" in m else None
        mesh = self.file("model.mesh", m["mesh"], MESH_SUFFIXES, "a closed mesh") if "mesh" in m else None
        builtin = self.builtin(m["builtin"]) if "builtin" in m else None
        shell = self.shell(m["shell"]) if "shell" in m else None

        patch = 0
        if "patch" in m:
            patch = self.integer("model.patch", m["patch"], 0)
            if kind is not None and kind != "nurbs" and patch is not None:
                self.bad("model.patch", "only used with a NURBS file", f"patch with {kind}",
                         "model.patch only together with model.nurbs")
            patch = patch or 0

        cage = None
        if "cage" in m:
            cage = self.cage(m["cage"])
            if kind is not None and kind != "mesh":
                self.bad("model.cage", "only used with a mesh", f"a cage with {kind}",
                         "model.cage only together with model.mesh")

        units = self.enum("model.units", m.get("units", "mm"), tuple(UNIT_SCALE)) or "mm"
        size = self.number("model.size", m.get("size"), above=0, allow_none=True)
        repair = self.boolean("model.repair", m.get("repair", False))
        if repair and kind is not None and kind != "mesh":
            self.bad("model.repair", "only used with a mesh", f"true with {kind}",
                     "model.repair only together with model.mesh")
        if kind == "mesh" and cage is None:
            cage = CageSpec(type="box")
        return ModelSpec(nurbs=nurbs, patch=patch, builtin=builtin, mesh=mesh, shell=shell, cage=cage, units=units,
                         unit_scale=UNIT_SCALE[units], size=size, repair=bool(repair))

    def shell(self, value):
        sh = self.mapping("model.shell", value, _SHELL_KEYS, allow_none=False)
        if sh is None:
            return None
        ok = True
        for key in ("surface", "thickness"):
            if key not in sh:
                self.bad(f"model.shell.{key}", "missing", "nothing",
                         "a surface file" if key == "surface" else "the wall thickness in mm, e.g. 4")
                ok = False
        surface = (self.file("model.shell.surface", sh["surface"], SURFACE_SUFFIXES, "a NURBS surface")
                   if "surface" in sh else None)
        thickness = self.number("model.shell.thickness", sh["thickness"], above=0) if "thickness" in sh else None
        patch = self.integer("model.shell.patch", sh.get("patch", 0), 0)
        side = sh.get("side", "inward")
        sides = f"{_one_of(_SHELL_SIDES)}, or the share of the wall outside the surface, 0 to 1"
        if isinstance(side, bool) or not isinstance(side, (str, int, float)):
            self.bad("model.shell.side", "not a side", _show(side), sides)
            side = None
        elif isinstance(side, str):
            if side.strip().lower() not in _SHELL_SIDES:
                self.bad("model.shell.side", "unknown value" + _suggest(side, _SHELL_SIDES), _show(side), sides)
            side = side.strip().lower() if side.strip().lower() in _SHELL_SIDES else None
        else:
            side = self.number("model.shell.side", side, at_least=0, at_most=1,
                               why=" (the share of the wall outside the surface)")
        if not ok or surface is None or thickness is None or patch is None or side is None:
            return None
        return ShellSpec(surface=surface, thickness=float(thickness), patch=int(patch), side=side)

    def texture(self, value):
        if value is None:
            return None
        t = self.mapping("texture", value, _TEXTURE_KEYS, allow_none=False)
        if t is None:
            return None
        if "image" not in t:
            self.bad("texture.image", "missing", "nothing", "an image file (.jpg or .png)")
            return None
        image = self.file("texture.image", t["image"], IMAGE_SUFFIXES, "an image")
        face = self.enum("texture.face", t.get("face", "w_max"), TEXTURE_FACES)
        transpose = self.boolean("texture.transpose", t.get("transpose", False))
        if image is None or face is None or transpose is None:
            return None
        return TextureSpec(image=image, face=face, transpose=bool(transpose))

    def builtin(self, value):
        if isinstance(value, str):  # `builtin: twisted-torus` is shorthand for {type: twisted-torus}
            value = {"type": value}
        if not isinstance(value, dict):
            self.bad("model.builtin", "not a mapping", _show(value),
                     "a mapping such as {type: twisted-torus, major_radius: 60}")
            return None
        out, ok = {}, True
        for key, item in value.items():
            path = _path_join("model.builtin", key if isinstance(key, str) else str(key))
            if not isinstance(key, str):
                self.bad(path, "not a parameter name", _show(key), "a text key")
                ok = False
            elif isinstance(item, (str, int, float, bool)) and not (
                    isinstance(item, float) and not math.isfinite(item)):
                out[key] = item
            elif isinstance(item, list) and all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                                and math.isfinite(x) for x in item):
                out[key] = list(item)
            else:
                self.bad(path, "not a simple parameter", _show(item), "a number, text, boolean or list of numbers")
                ok = False
        if "type" not in value:
            self.bad("model.builtin.type", "missing", "nothing", "the name of a built-in shape, e.g. twisted-torus")
            ok = False
        elif not isinstance(value["type"], str) or not value["type"]:
            self.bad("model.builtin.type", "not a shape name", _show(value["type"]),
                     "the name of a built-in shape, e.g. twisted-torus")
            ok = False
        if ok:  # its parameters' ranges too, so that the message names the spec file and comes with the others
            from .models import validate_builtin

            try:
                validate_builtin(out)
            except SpecError as e:
                self.problems.extend(e.problems)
                ok = False
        return out if ok else None

    def cage(self, value):
        if isinstance(value, str):
            kind = self.enum("model.cage", value, CAGE_TYPES)
            return CageSpec(type=kind) if kind else None
        if not isinstance(value, dict):
            self.bad("model.cage", "not a cage", _show(value),
                     f"{_one_of(CAGE_TYPES)}, {{nurbs: file}} or {{type: box, padding: 2, control_points: [4, 4, 4]}}")
            return None
        c = self.mapping("model.cage", value, _CAGE_KEYS)
        if c is None:
            return None
        if "nurbs" in c:
            wrong = [k for k in ("type", "padding", "control_points") if k in c]
            if wrong:
                self.bad("model.cage", "a NURBS cage takes no shape keys", "nurbs with " + ", ".join(wrong),
                         "either {nurbs: file, patch: k} or {type: ..., padding: ..., control_points: ...}")
            path = self.file("model.cage.nurbs", c["nurbs"], NURBS_SUFFIXES, "a NURBS cage")
            patch = self.integer("model.cage.patch", c.get("patch", 0), 0)
            return CageSpec(type="nurbs", nurbs=path, patch=patch or 0, padding=0.0)
        if "patch" in c:
            self.bad("model.cage.patch", "only used with a NURBS cage", _show(c["patch"]),
                     "model.cage.patch only together with model.cage.nurbs")
        if "type" not in c:
            self.bad("model.cage.type", "missing", "nothing", _one_of(CAGE_TYPES) + ", or give model.cage.nurbs")
            kind = None
        else:
            kind = self.enum("model.cage.type", c["type"], CAGE_TYPES)
        padding = self.number("model.cage.padding", c.get("padding", DEFAULT_CAGE_PADDING), at_least=0)
        cps = None
        if c.get("control_points") is not None:
            cps = self.triple("model.cage.control_points", c["control_points"], 2, allow_one=True)
        if kind is None or padding is None:
            return None
        return CageSpec(type=kind, padding=padding, control_points=cps)

    def triple(self, path, value, minimum, allow_one=False):
        """Three integers >= minimum (u, v, w), or with allow_one a single integer for all three."""
        expected = f"3 integers [u, v, w], each >= {minimum}" + (" (or one integer for all)" if allow_one else "")
        if allow_one and isinstance(value, int) and not isinstance(value, bool):
            n = self.integer(path, value, minimum)
            return None if n is None else (n, n, n)
        if not isinstance(value, list):
            if isinstance(value, (int, float)) and not isinstance(value, bool) and not allow_one:
                self.bad(path, "a single number", _show(value), expected)
            else:
                self.bad(path, "not a list", _show(value), expected)
            return None
        if len(value) != 3:
            self.bad(path, "wrong number of entries", _show(value), expected)
            return None
        items = [self.integer(_path_join(path, i), x, minimum) for i, x in enumerate(value)]
        return None if any(x is None for x in items) else tuple(items)

    def axis(self, path, value):
        if isinstance(value, str) and value.strip().lower() in AXES:
            return AXES.index(value.strip().lower())
        if isinstance(value, int) and not isinstance(value, bool):
            self.bad(path, "an axis number instead of its name", _show(value), "an axis name: u, v or w")
        elif isinstance(value, str):
            self.bad(path, "unknown axis" + _suggest(value, AXES), _show(value), "an axis name: u, v or w")
        else:
            self.bad(path, "not an axis name", _show(value), "an axis name: u, v or w")
        return None

    def splits(self, value, grid, mesh=False):
        """mesh: the model is a mesh, whose axes default to balanced splits (equal volumes of the mesh)."""
        default = "balanced" if mesh else "uniform"
        if value is not None and not isinstance(value, dict):
            self.bad("splits", "not a mapping", _show(value),
                     "a mapping by axis, e.g. {w: uniform, u: [0.3, 0.7]}")
            return (default,) * 3
        s = self.mapping("splits", value, AXES) or {}
        out = []
        for k, ax in enumerate(AXES):
            if ax not in s or s[ax] is None:
                out.append(default)
                continue
            out.append(self.split(f"splits.{ax}", s[ax], None if grid is None else grid[k], k))
            if out[-1] == "balanced" and not mesh:
                self.bad(f"splits.{ax}", "balanced splits follow a mesh's volume", "balanced without a mesh model",
                         "uniform, knots or a list of parameters")
        return tuple(out)

    def split(self, path, value, cells, k):
        expected_list = "a list of interior parameters"
        if cells is not None:
            expected_list = f"a list of {cells - 1} = grid[{k}] - 1 interior parameters"
        if isinstance(value, str) or not isinstance(value, list):
            if isinstance(value, str):
                mode = self.enum(path, value, SPLIT_MODES)
            else:
                self.bad(path, "not a split rule", _show(value), f"uniform, knots, balanced, or {expected_list}")
                mode = None
            return mode or "uniform"
        params = []
        for i, x in enumerate(value):
            params.append(self.number(_path_join(path, i), x))
        if cells is not None and len(value) != cells - 1:
            self.bad(path, "wrong number of interior parameters", f"{len(value)} parameters {_repr.repr(value)}",
                     f"{cells - 1} = grid[{k}] - 1, one between each pair of neighbouring pieces")
            return "uniform"
        if any(p is None for p in params):
            return "uniform"
        for i in range(1, len(params)):
            if not params[i] > params[i - 1]:
                self.bad(path, "not strictly increasing", _show(value),
                         f"each parameter larger than the one before (entry {i}: {_num(params[i])} "
                         f"after {_num(params[i - 1])})")
                return "uniform"
        return tuple(params)

    def periodic(self, value):
        if value is None:
            return ()
        if isinstance(value, str):  # `periodic: w` for a single axis
            value = [value]
        if not isinstance(value, list):
            self.bad("periodic", "not a list of axes", _show(value), "a list of axis names, e.g. [w]")
            return ()
        seen = []
        for i, item in enumerate(value):
            ax = self.axis(_path_join("periodic", i), item)
            if ax is None:
                continue
            if ax in seen:
                self.bad(_path_join("periodic", i), "axis given twice", _show(item), "each axis at most once")
                continue
            seen.append(ax)
        return tuple(sorted(seen))

    def randomize(self, value):
        if value is None:
            return None
        r = self.mapping("randomize", value, _RANDOMIZE_KEYS)
        if r is None:
            return None
        seed = self.integer("randomize.seed", r.get("seed", 0), 0)
        amplitude = self.number("randomize.amplitude", r.get("amplitude", 0.25), at_least=0)
        cps = self.integer("randomize.control_points", r.get("control_points", 6), 4)
        if seed is None or amplitude is None or cps is None or amplitude == 0:
            return None
        return RandomizeSpec(seed=seed, amplitude=amplitude, control_points=cps)

    def joints(self, value):
        j = self.mapping("joints", value, _JOINT_KEYS)
        if j is None:
            return JointSpec()
        d = JointSpec()
        style = self.enum("joints.style", j.get("style", d.style), JOINT_STYLES)
        shape = self.enum("joints.shape", j.get("shape", d.shape), JOINT_SHAPES)
        space = self.enum("joints.space", j.get("space", d.space), JOINT_SPACES)
        radius = self.number("joints.radius", j.get("radius"), above=0, allow_none=True)
        length = self.number("joints.length", j.get("length"), above=0, allow_none=True)
        why = "; a print clearance is a few tenths of a millimetre, 0.1 to 0.4 mm for most printers"
        clearance = self.number("joints.clearance", j.get("clearance", d.clearance), at_least=0,
                                at_most=_MAX_CLEARANCE, why=why)
        axial = self.number("joints.axial_clearance", j.get("axial_clearance", d.axial_clearance), at_least=0,
                            at_most=_MAX_CLEARANCE, why=why)
        if clearance is not None and radius is not None and clearance >= radius:
            self.bad("joints.clearance", "not smaller than the pin radius", _show(j.get("clearance", d.clearance)),
                     f">= 0 and < joints.radius = {_num(radius)}; or a radius > {_num(clearance)}")
        min_radius = self.number("joints.min_radius", j.get("min_radius", d.min_radius), above=0)
        min_length = self.number("joints.min_length", j.get("min_length", d.min_length), above=0)
        allow = self.allow(j.get("allow"))
        return JointSpec(style=style or d.style, shape=shape or d.shape, radius=radius, length=length,
                         clearance=d.clearance if clearance is None else clearance,
                         axial_clearance=d.axial_clearance if axial is None else axial, space=space or d.space,
                         min_radius=d.min_radius if min_radius is None else min_radius,
                         min_length=d.min_length if min_length is None else min_length, allow=allow)

    def allow(self, value):
        """joints.allow: a list of JOINT_ALLOW words (or one word) -> sorted tuple."""
        if value is None:
            return ()
        items = [value] if isinstance(value, str) else value
        if not isinstance(items, (list, tuple)):
            self.bad("joints.allow", "not a list", _show(value), f"a list of {', '.join(JOINT_ALLOW)}, e.g. [loose]")
            return ()
        out = []
        for i, item in enumerate(items):
            if item not in JOINT_ALLOW:
                self.bad(_path_join("joints.allow", i), "unknown", _show(item), f"one of {', '.join(JOINT_ALLOW)}")
            elif item not in out:
                out.append(item)
        return tuple(sorted(out))

    def output(self, value, name):
        o = self.mapping("output", value, _OUTPUT_KEYS)
        if o is None:
            o = {}
        d = OutputSpec()
        directory = None
        if o.get("directory") is not None:
            raw = o["directory"]
            if not isinstance(raw, str) or not raw.strip():
                self.bad("output.directory", "not a folder path", _show(raw),
                         "a folder path, relative to the current directory")
            else:
                try:
                    directory = _resolve_dir(raw)
                    if directory.exists() and not directory.is_dir():
                        self.bad("output.directory", "is a file, not a folder", repr(str(directory)),
                                 "a folder path (it is created, or replaced with --force)")
                except (OSError, ValueError) as exc:
                    self.bad("output.directory", f"not a usable folder path ({getattr(exc, 'strerror', None) or exc})",
                             _show(raw), "a folder path, relative to the current directory")
                    directory = None
        if directory is None and name is not None:
            directory = _resolve_dir(Path("out") / name)
        fmt = self.enum("output.format", o.get("format", d.format), FORMATS)
        tol = self.number("output.tolerance", o.get("tolerance", d.tolerance), above=0)
        spacing = self.number("output.spacing", o.get("spacing", d.spacing), at_least=0)
        labels = self.boolean("output.labels", o.get("labels", d.labels))
        margin = self.number("output.margin", o.get("margin", d.margin), at_least=0)
        face_clearance = self.number("output.face_clearance", o.get("face_clearance", d.face_clearance),
                                     at_least=0)
        if face_clearance is not None and face_clearance > 1.0:
            self.bad("output.face_clearance", "would leave the pieces loose", _show(o.get("face_clearance")),
                     "a gap in mm from 0 to 1 (0.1 to 0.2 suits a 0.4 mm nozzle)")
            face_clearance = None
        plate = d.plate
        raw_plate = o.get("plate", list(d.plate))
        if not isinstance(raw_plate, list) or len(raw_plate) != 2:
            self.bad("output.plate", "not a width and a depth", _show(raw_plate), "2 numbers [x, y] in mm, each > 0")
        else:
            items = [self.number(_path_join("output.plate", i), x, above=0) for i, x in enumerate(raw_plate)]
            if all(x is not None for x in items):
                plate = tuple(items)
                if spacing is not None and 2 * spacing >= min(plate):
                    self.bad("output.spacing", "leaves no room on the plate", _show(o.get("spacing", d.spacing)),
                             f"less than half the plate's smaller side, < {_num(min(plate) / 2)}")
                if margin is not None and 2 * margin >= min(plate):
                    self.bad("output.margin", "leaves no room on the plate", _show(o.get("margin", d.margin)),
                             f"less than half the plate's smaller side, < {_num(min(plate) / 2)}")
        return OutputSpec(directory=directory, format=fmt or d.format, tolerance=tol or d.tolerance, plate=plate,
                          spacing=d.spacing if spacing is None else spacing,
                          labels=d.labels if labels is None else labels,
                          margin=d.margin if margin is None else margin,
                          face_clearance=d.face_clearance if face_clearance is None else face_clearance)


    def limits(self, value):
        """limits: {pieces: N, ...} raises the resource limits (limits.py) this spec means to pass."""
        d = Limits()
        m = self.mapping("limits", value, tuple(LIMIT_HELP))
        if m is None:
            return d
        raised = {}
        for key, item in m.items():
            if isinstance(item, float) and math.isfinite(item) and item == int(item) and abs(item) < 1e15:
                item = int(item)  # `triangles: 2e7` is a plain count
            n = self.integer(f"limits.{key}", item, 1, what=f"an integer ({LIMIT_HELP[key]}; default "
                                                          f"{getattr(d, key)})")
            if n is not None:
                raised[key] = n
        return dataclasses.replace(d, **raised)


_REQUIRED_HELP = {
    "name": "a name of letters, digits, '-' and '_'",
    "model": "a mapping with one of nurbs, builtin, mesh, shell",
    "grid": "3 integers [u, v, w], each >= 1",
}


def _resolve_dir(p) -> Path:
    return (Path.cwd() / Path(p).expanduser()).resolve()


# ----------------------------------------------------------------------------------------------------
# Loading


def _yaml_problem(exc: Exception) -> str:
    mark = getattr(exc, "problem_mark", None) or getattr(exc, "context_mark", None)
    where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
    problem = getattr(exc, "problem", None) or str(exc) or type(exc).__name__
    problem = " ".join(str(problem).split())
    if "constructor for the tag" in problem:
        tag = re.search(r"'([^']*)'", problem)
        tag = tag.group(1).replace("tag:yaml.org,2002:", "!!") if tag else "?"
        return (f"spec: YAML tag not allowed{where} (got {tag!r}, expected plain YAML: mappings, lists, "
                f"texts, numbers and booleans)")
    if isinstance(exc, RecursionError):
        problem = "nested too deeply"
    elif isinstance(exc, ValueError) and not isinstance(exc, yaml.YAMLError):
        # PyYAML builds dates from anything shaped like one, and fails on impossible ones
        return (f"spec: a value shaped like a date is not a real date (got {_repr.repr(problem)}, expected a "
                f"valid date, or quotes around the text)")
    return f"spec: not valid YAML{where} (got {_repr.repr(problem)}, expected a YAML mapping)"


def _duplicate_keys(text: str) -> list[str]:
    """Keys given twice in one mapping (safe_load silently keeps the last one). Composing builds nodes only."""
    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
    except Exception:  # noqa: BLE001 - the parse already succeeded; this check is best effort
        return []
    problems, stack, seen_nodes = [], [("", root)], set()
    while stack:
        path, node = stack.pop()
        if node is None or id(node) in seen_nodes:
            continue
        seen_nodes.add(id(node))
        if isinstance(node, yaml.MappingNode):
            lines: dict = {}
            for key_node, value_node in node.value:
                if isinstance(key_node, yaml.ScalarNode):
                    lines.setdefault(key_node.value, []).append(key_node.start_mark.line + 1)
                    stack.append((_path_join(path, key_node.value), value_node))
            for key, where in lines.items():
                if len(where) > 1:
                    problems.append(f"{_path_join(path, key)}: given more than once (got lines "
                                    f"{', '.join(map(str, where))}, expected each key once)")
        elif isinstance(node, yaml.SequenceNode):
            for i, item in enumerate(node.value):
                stack.append((_path_join(path or "spec", i), item))
    return sorted(problems)


def load_spec_text(text: str, source: Path | str | None = None) -> Spec:
    """Parse and check a spec given as text; relative model paths are read from source's folder."""
    source = Path(source if source is not None else Path.cwd() / "spec.yaml").expanduser().resolve()
    try:
        data = yaml.safe_load(text)
    except Exception as exc:  # noqa: BLE001 - any parse failure (YAMLError, bad dates, deep nesting) is a bad spec
        raise SpecError([_yaml_problem(exc)], source=source) from None
    if data is None:
        raise SpecError(["spec: the file is empty (got nothing, expected a mapping with at least name, model "
                         "and grid)"], source=source)
    if not isinstance(data, dict):
        raise SpecError([f"spec: the top level is not a mapping (got {_show(data)}, expected a mapping with "
                         f"keys {', '.join(_TOP_KEYS)})"], source=source)
    return _check(data, source, _duplicate_keys(text))


def load_spec(path) -> Spec:
    """Read and check a spec file -> Spec, or raise one SpecError listing every mistake."""
    path = Path(path).expanduser()
    try:
        if path.exists() and not path.is_dir() and not path.is_file():  # reading a FIFO would wait forever
            raise SpecError([f"spec: not a regular file (got {str(path)!r}, a FIFO, device or socket, expected a "
                             "YAML file)"], source=path)
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise SpecError([f"spec: file not found (got {str(path.resolve())!r}, expected an existing YAML file)"],
                        source=path) from None
    except IsADirectoryError:
        raise SpecError([f"spec: is a folder (got {str(path.resolve())!r}, expected a YAML file)"],
                        source=path) from None
    except UnicodeDecodeError as exc:
        raise SpecError([f"spec: not a text file (got undecodable byte at offset {exc.start}, expected UTF-8 "
                         "YAML)"], source=path) from None
    except OSError as exc:
        raise SpecError([f"spec: cannot read the file (got {exc.strerror or exc}, expected a readable YAML "
                         "file)"], source=path) from None
    except ValueError as exc:  # a NUL byte in the path
        raise SpecError([f"spec: not a usable path (got {str(path)!r}: {exc}, expected a file path)"]) from None
    return load_spec_text(text, source=path)


def _check(data: dict, source: Path, problems: list[str]) -> Spec:
    c = _Checker(source.parent)
    c.problems.extend(problems)
    top = c.mapping("", data, _TOP_KEYS)

    def required(key, check):
        if key in top:
            return check(top[key])
        c.bad(key, "missing", "nothing", _REQUIRED_HELP[key])
        return None
    name = required("name", c.name)
    model = required("model", c.model)
    grid = required("grid", lambda value: c.triple("grid", value, 1))
    splits = c.splits(top.get("splits"), grid, mesh=model is not None and model.mesh is not None)
    periodic = c.periodic(top.get("periodic"))
    randomize = c.randomize(top.get("randomize"))
    joints = c.joints(top.get("joints"))
    output = c.output(top.get("output"), name)
    limits = c.limits(top.get("limits"))
    texture = c.texture(top.get("texture"))
    if texture is not None and model is not None and model.mesh is not None:
        # the faces of a cage around a mesh are not the mesh's surface: nothing would take the colours
        c.bad("texture", "not for a mesh model", "a texture with model.mesh",
              "texture only with model.nurbs, model.builtin or model.shell")
    if c.problems:
        raise SpecError(c.problems, source=source)
    return Spec(name=name, model=model, grid=grid, splits=splits, periodic=periodic, randomize=randomize,
                joints=joints, output=output, texture=texture, limits=limits, source=source, raw=data)


# ----------------------------------------------------------------------------------------------------
# Overrides and the report form


def with_overrides(spec: Spec, output_dir=None, fmt=None, seed=None, allow_large=False) -> Spec:
    """The spec with the CLI's -o / --format / --seed / --allow-large applied. --seed only matters when randomize
    is on."""
    c = _Checker(spec.source.parent if spec.source else Path.cwd())
    output, randomize = spec.output, spec.randomize
    limits = dataclasses.replace(spec.limits, unlimited=True) if allow_large else spec.limits
    if output_dir is not None:
        try:
            directory = _resolve_dir(output_dir)
            if directory.exists() and not directory.is_dir():
                c.bad("output.directory", "is a file, not a folder", repr(str(directory)), "a folder path (-o)")
            output = dataclasses.replace(output, directory=directory)
        except (OSError, ValueError) as exc:
            c.bad("output.directory", f"not a usable folder path ({getattr(exc, 'strerror', None) or exc})",
                  _show(str(output_dir)), "a folder path (-o)")
    if fmt is not None:
        value = c.enum("output.format", fmt, FORMATS)
        if value:
            output = dataclasses.replace(output, format=value)
    if seed is not None:
        value = c.integer("randomize.seed", seed, 0)
        if value is not None and randomize is not None:
            randomize = dataclasses.replace(randomize, seed=value)
    if c.problems:
        raise SpecError(c.problems, source=spec.source)
    return dataclasses.replace(spec, output=output, randomize=randomize, limits=limits)


def spec_to_dict(spec: Spec) -> dict:
    """The spec with every default filled in; JSON-serialisable, and loadable again as a spec."""
    m = spec.model
    model: dict = {}
    if m.nurbs is not None:
        model.update(nurbs=str(m.nurbs), patch=m.patch)
    elif m.builtin is not None:
        model["builtin"] = dict(m.builtin)
    elif m.shell is not None:
        model["shell"] = {"surface": str(m.shell.surface), "thickness": m.shell.thickness, "patch": m.shell.patch,
                          "side": m.shell.side}
    elif m.mesh is not None:
        model["mesh"] = str(m.mesh)
        cage = m.cage or CageSpec(type="box")
        if cage.type == "nurbs":
            model["cage"] = {"nurbs": str(cage.nurbs), "patch": cage.patch}
        else:
            model["cage"] = {"type": cage.type, "padding": cage.padding,
                             "control_points": None if cage.control_points is None else list(cage.control_points)}
        model["repair"] = m.repair
    model.update(units=m.units, size=m.size)
    r = spec.randomize
    j, o = spec.joints, spec.output
    out = {
        "name": spec.name,
        "model": model,
        "grid": list(spec.grid),
        "splits": {ax: (list(s) if isinstance(s, tuple) else s) for ax, s in zip(AXES, spec.splits, strict=True)},
        "periodic": [AXES[k] for k in spec.periodic],
        "randomize": None if r is None else {"seed": r.seed, "amplitude": r.amplitude,
                                             "control_points": r.control_points},
        "joints": {"style": j.style, "shape": j.shape, "radius": j.radius, "length": j.length,
                   "clearance": j.clearance, "axial_clearance": j.axial_clearance, "space": j.space,
                   "min_radius": j.min_radius, "min_length": j.min_length, "allow": list(j.allow)},
        "output": {"directory": None if o.directory is None else str(o.directory), "format": o.format,
                   "tolerance": o.tolerance, "plate": list(o.plate), "spacing": o.spacing, "labels": o.labels,
                   "margin": o.margin, "face_clearance": o.face_clearance},
        **({} if spec.texture is None else {"texture": {"image": str(spec.texture.image), "face": spec.texture.face,
                                                         "transpose": spec.texture.transpose}}),
    }
    raised = {k: getattr(spec.limits, k) for k in LIMIT_HELP if getattr(spec.limits, k) != getattr(Limits(), k)}
    if raised:
        out["limits"] = raised
    return out
