"""Material categories, their parameter ranges, and the mapping to Blender 5's Principled BSDF.

Design notes (why the ranges are what they are, the near-mirror exclusion, near mirrors
measured in Blender 5.0.1, the reason for each socket): ``docs/bsdf.md``.

Paper parameters (Disney 2012 "principled" model, as in CNN-PS / CyclesPS):
``base_color`` (RGB), ``metallic``, ``specular``, ``roughness``, ``sheen``, ``sheen_tint``.

Categories and default ranges (uniform draws, one row per superpixel); the first three
are the paper's (:data:`DEFAULT_CATEGORIES`), ``narrow`` (narrow-lobe glossy dielectrics)
is opt-in through ``materials.categories``:

=========  ==========  ========  ========  =========  =====  ==========
category   base_color  metallic  specular  roughness  sheen  sheen_tint
=========  ==========  ========  ========  =========  =====  ==========
diffuse    0–1         0         0–1       0–1        0–1    0–1
specular   0–1         0         0–4       0–1        0–1    0–1
metallic   0–1         1         0–1       0.3–0.7    0–1    0–1
narrow     0–1         0         0.5–2     0.02–0.15  0      0
=========  ==========  ========  ========  =========  =====  ==========

- :class:`MaterialRanges` (one :class:`CategoryRanges` per category) from params.yaml's
  ``materials.ranges`` with :meth:`MaterialRanges.from_dict`: partial overrides of the
  defaults, snake_case or camelCase names; ``ConfigError`` unless lo ≤ hi inside the
  physical limits (:data:`PHYSICAL_LIMITS`: [0, 1], specular [0, 12]).
- :func:`sample_parameters` ``(ranges, n, rng)``: n rows, ``base_color`` (n, 3), the
  others (n,), float32, in a fixed draw order. Where ``specular`` > ``high_specular``
  (default 1), ``roughness`` is drawn from [max(lo, ``high_specular_min_roughness``), hi]
  (default floor 0.05; 0.02 for narrow): no strong near-mirror dielectric.
- :func:`to_blender_inputs` ``(params)``: Principled BSDF socket values (pure: no bpy),
  scalars or per-pixel arrays: ``Base Color`` = base_color, ``Metallic``, ``Roughness``
  as given; ``IOR`` = 1.5 and ``Specular IOR Level`` = specular (Cycles' F0 = 0.08 ·
  level, Disney's F0 = 0.08 · specular); ``Specular Tint`` white; ``Sheen Weight`` =
  sheen · (1 − metallic); ``Sheen Tint`` = mix(white, base_color, sheen_tint);
  ``Sheen Roughness`` 0.5; ``Diffuse Roughness`` 0; Subsurface, Transmission, Coat,
  Emission, Anisotropic, Thin Film 0; Alpha 1.
- :func:`specular_to_ior` / :func:`ior_to_specular` / :func:`blender_f0`: the same F0
  through the IOR (1.5 at specular 0.5).

Example::

    rng = np.random.default_rng(0)
    rows = sample_parameters(MaterialRanges().get("specular"), 4, rng)
    inputs = to_blender_inputs({k: v[0] for k, v in rows.items()})   # node.inputs[name].default_value
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, fields, make_dataclass, replace
from functools import partial

import numpy as np

from cnnps.infra.errors import ConfigError

DEFAULT_CATEGORIES = ("diffuse", "specular", "metallic")  # the paper's: drawn unless told otherwise
PARAM_NAMES = ("base_color", "metallic", "specular", "roughness", "sheen", "sheen_tint")
RANGE_NAMES = PARAM_NAMES
PHYSICAL_LIMITS = {
    "base_color": (0.0, 1.0),
    "metallic": (0.0, 1.0),
    "specular": (0.0, 12.0),  # F0 = 0.08 s < 1
    "roughness": (0.0, 1.0),
    "sheen": (0.0, 1.0),
    "sheen_tint": (0.0, 1.0),
}
_ALIASES = {"baseColor": "base_color", "sheenTint": "sheen_tint", "basecolor": "base_color", "sheentint": "sheen_tint"}


def _pair(value, name: str, where: str) -> tuple[float, float]:
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        lo = hi = float(value)
    else:
        try:
            lo, hi = (float(v) for v in value)
        except (TypeError, ValueError):
            raise ConfigError(f"{where}.{name} must be a number or [lo, hi], got {value!r}") from None
    plo, phi = PHYSICAL_LIMITS[name]
    if not (np.isfinite(lo) and np.isfinite(hi)):
        raise ConfigError(f"{where}.{name} must be finite, got {value!r}")
    if lo > hi:
        raise ConfigError(f"{where}.{name}: lo {lo} > hi {hi}")
    if lo < plo or hi > phi:
        raise ConfigError(f"{where}.{name}: [{lo}, {hi}] is outside the physical limits [{plo}, {phi}]")
    return (lo, hi)


@dataclass(frozen=True)
class CategoryRanges:
    """Uniform ranges ``(lo, hi)`` of one category, plus the near-mirror exclusion."""

    base_color: tuple[float, float] = (0.0, 1.0)
    metallic: tuple[float, float] = (0.0, 0.0)
    specular: tuple[float, float] = (0.0, 1.0)
    roughness: tuple[float, float] = (0.0, 1.0)
    sheen: tuple[float, float] = (0.0, 1.0)
    sheen_tint: tuple[float, float] = (0.0, 1.0)
    high_specular: float = 1.0
    high_specular_min_roughness: float = 0.05
    name: str = "category"

    def __post_init__(self):
        where = f"materials.ranges.{self.name}"
        for n in RANGE_NAMES:
            object.__setattr__(self, n, _pair(getattr(self, n), n, where))
        if not 0 <= self.high_specular_min_roughness <= 1:
            raise ConfigError(f"{where}.high_specular_min_roughness must be in [0, 1], got {self.high_specular_min_roughness}")
        if not self.high_specular >= 0:
            raise ConfigError(f"{where}.high_specular must be >= 0, got {self.high_specular}")
        if self.specular[1] > self.high_specular and max(self.roughness[0], self.high_specular_min_roughness) > self.roughness[1]:
            raise ConfigError(
                f"{where}: roughness range {list(self.roughness)} is entirely below high_specular_min_roughness "
                f"{self.high_specular_min_roughness} while specular may exceed {self.high_specular}"
            )

    @classmethod
    def from_dict(cls, d: dict, name: str = "category", base: "CategoryRanges | None" = None) -> "CategoryRanges":
        """Ranges from a mapping (params.yaml), missing keys taken from ``base`` (or the class defaults)."""
        if not isinstance(d, dict):
            raise ConfigError(f"materials.ranges.{name} must be a mapping, got {type(d).__name__}")
        known = {f.name for f in fields(cls)} - {"name"}
        kw = {}
        for k, v in d.items():
            k2 = _ALIASES.get(k, k)
            if k2 == "name":
                continue
            if k2 not in known:
                raise ConfigError(f"materials.ranges.{name}: unknown key {k!r} (known: {', '.join(sorted(known))})")
            kw[k2] = v
        start = base if base is not None else cls(name=name)
        return replace(start, name=name, **kw)

    def to_dict(self) -> dict:
        d = asdict(self)
        d.pop("name")
        return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}


# Every category known and its default ranges, declared once: the keyword arguments of its
# CategoryRanges (the rest at the class defaults). CATEGORIES, MaterialRanges' fields, the
# checks of every section that names a category and `cnnps render`'s materials follow from it.
CATEGORY_DEFAULTS: dict[str, dict] = {
    "diffuse": {},
    "specular": {"specular": (0.0, 4.0)},
    "metallic": {"metallic": (1.0, 1.0), "roughness": (0.3, 0.7)},
    "narrow": {"specular": (0.5, 2.0), "roughness": (0.02, 0.15), "sheen": (0.0, 0.0), "sheen_tint": (0.0, 0.0),
               "high_specular_min_roughness": 0.02},
}
CATEGORIES = tuple(CATEGORY_DEFAULTS)  # every category known


def _default(category: str) -> CategoryRanges:
    if category not in CATEGORY_DEFAULTS:
        raise ConfigError(f"unknown material category {category!r} (choose from {', '.join(CATEGORIES)})")
    return CategoryRanges(**CATEGORY_DEFAULTS[category], name=category)


class _MaterialRangesMethods:
    """Ranges of all categories (the ``materials.ranges`` section of params.yaml): a frozen
    dataclass with one :class:`CategoryRanges` field per category of
    :data:`CATEGORY_DEFAULTS`, in its order, each at its defaults unless given."""

    @classmethod
    def from_dict(cls, d: dict | None, where: str = "materials") -> "MaterialRanges":
        """Per-category overrides of the paper's defaults, e.g. ``{"specular": {"specular": [0, 2]}}``;
        messages name ``where.ranges`` (the params section: ``materials``, ``eval``, ...)."""
        if d is None:
            return cls()
        if not isinstance(d, dict):
            raise ConfigError(f"{where}.ranges must be a mapping of categories, got {type(d).__name__}")
        kw = {}
        for cat, sub in d.items():
            c = str(cat).lower()
            if c not in CATEGORIES:
                raise ConfigError(f"{where}.ranges: unknown category {cat!r} (choose from {', '.join(CATEGORIES)})")
            kw[c] = CategoryRanges.from_dict(sub or {}, c, base=_default(c))
        return cls(**kw)

    def get(self, category: str) -> CategoryRanges:
        c = category.lower()
        if c not in CATEGORIES:
            raise ConfigError(f"unknown material category {category!r} (choose from {', '.join(CATEGORIES)})")
        return getattr(self, c)

    def to_dict(self) -> dict:
        return {c: self.get(c).to_dict() for c in CATEGORIES}


MaterialRanges = make_dataclass(
    "MaterialRanges", [(c, CategoryRanges, field(default_factory=partial(_default, c))) for c in CATEGORIES],
    bases=(_MaterialRangesMethods,), frozen=True, namespace={"__doc__": _MaterialRangesMethods.__doc__})
MaterialRanges.__module__ = __name__


def sample_parameters(ranges: CategoryRanges, n: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """``n`` parameter rows drawn uniformly from ``ranges``: base_color (n,3), others (n,), float32.

    Draw order is fixed (base_color, metallic, specular, roughness, sheen, sheen_tint),
    so a seed gives the same table whatever the ranges are.
    """
    u = {
        "base_color": rng.random((n, 3)),
        "metallic": rng.random(n),
        "specular": rng.random(n),
        "roughness": rng.random(n),
        "sheen": rng.random(n),
        "sheen_tint": rng.random(n),
    }
    out = {}
    for name in PARAM_NAMES:
        lo, hi = getattr(ranges, name)
        out[name] = lo + u[name] * (hi - lo)
    # near-mirror exclusion: high specular draws roughness above the floor
    lo, hi = ranges.roughness
    floor = max(lo, ranges.high_specular_min_roughness)
    high = out["specular"] > ranges.high_specular
    if high.any() and floor > lo:
        out["roughness"][high] = floor + u["roughness"][high] * (hi - floor)
    return {k: v.astype(np.float32) for k, v in out.items()}


# --------------------------------------------------------------------------- Blender 5


def specular_to_ior(s):
    """IOR whose normal-incidence reflectance equals Disney's F0 = 0.08·s (1.5 at s = 0.5)."""
    s = np.asarray(s, dtype=np.float64)
    if np.any(s < 0) or np.any(s >= 12.5):
        raise ValueError("specular must be in [0, 12.5)")
    r = 2.0 / (1.0 - np.sqrt(0.08 * s)) - 1.0
    return float(r) if r.ndim == 0 else r


def ior_to_specular(ior):
    """Inverse of :func:`specular_to_ior`: s = ((ior − 1)/(ior + 1))² / 0.08."""
    ior = np.asarray(ior, dtype=np.float64)
    s = ((ior - 1.0) / (ior + 1.0)) ** 2 / 0.08
    return float(s) if s.ndim == 0 else s


def blender_f0(inputs: dict) -> np.ndarray | float:
    """Dielectric F0 Cycles derives from ``IOR`` and ``Specular IOR Level`` (for tests and checks)."""
    ior = np.asarray(inputs["IOR"], dtype=np.float64)
    level = np.maximum(np.asarray(inputs["Specular IOR Level"], dtype=np.float64), 0.0)
    f0 = ((ior - 1.0) / (ior + 1.0)) ** 2 * 2.0 * level
    return float(f0) if f0.ndim == 0 else f0


def _rgba(c):
    c = np.asarray(c, dtype=np.float64)
    if c.shape[-1] != 3:
        raise ValueError(f"a colour must have 3 channels, got shape {c.shape}")
    out = np.concatenate([c, np.ones(c.shape[:-1] + (1,))], axis=-1)
    return tuple(float(v) for v in out) if out.ndim == 1 else out


def to_blender_inputs(params: dict) -> dict:
    """Principled BSDF input values (Blender 5 socket names) for paper parameters.

    ``params``: ``base_color`` (3,) or (...,3) and ``metallic``, ``specular``, ``roughness``,
    ``sheen``, ``sheen_tint`` scalars or (...) arrays (e.g. a :class:`MaterialMaps.table`
    or per-pixel maps). Scalars give floats and RGBA 4-tuples (ready for
    ``node.inputs[name].default_value``); arrays give arrays, colours with a last axis
    of 4 (RGBA, alpha 1). See the module docstring for the mapping and its reasons.
    """
    missing = [k for k in PARAM_NAMES if k not in params]
    if missing:
        raise ValueError(f"missing paper parameters: {missing}")
    base = np.asarray(params["base_color"], dtype=np.float64)
    metallic = np.asarray(params["metallic"], dtype=np.float64)
    specular = np.asarray(params["specular"], dtype=np.float64)
    roughness = np.asarray(params["roughness"], dtype=np.float64)
    sheen = np.asarray(params["sheen"], dtype=np.float64)
    sheen_tint = np.asarray(params["sheen_tint"], dtype=np.float64)

    def val(x):
        x = np.asarray(x, dtype=np.float64)
        return float(x) if x.ndim == 0 else x

    tint = 1.0 + sheen_tint[..., None] * (base - 1.0)  # mix(white, base, sheen_tint)
    shape = roughness.shape
    zeros = np.zeros(shape)
    white = np.ones(shape + (3,))
    return {
        "Base Color": _rgba(base),
        "Metallic": val(metallic),
        "Roughness": val(roughness),
        "IOR": val(np.full(shape, 1.5)),
        "Specular IOR Level": val(specular),
        "Specular Tint": _rgba(white),
        "Sheen Weight": val(sheen * (1.0 - metallic)),
        "Sheen Tint": _rgba(tint),
        "Sheen Roughness": val(np.full(shape, 0.5)),
        "Diffuse Roughness": val(zeros),
        "Subsurface Weight": val(zeros),
        "Transmission Weight": val(zeros),
        "Coat Weight": val(zeros),
        "Anisotropic": val(zeros),
        "Emission Strength": val(zeros),
        "Thin Film Thickness": val(zeros),
        "Alpha": val(np.ones(shape)),
    }


def checked_ranges(where: str, ranges) -> MaterialRanges:
    """A params section's ``ranges`` (None, a mapping of per-category overrides, or a
    :class:`MaterialRanges`) as :class:`MaterialRanges`; the one conversion and check that
    ``materials``, ``eval`` and ``train.synthesis`` share, messages naming ``where.ranges``."""
    if ranges is None:
        return MaterialRanges()
    if isinstance(ranges, MaterialRanges):
        return ranges
    if isinstance(ranges, Mapping):
        return MaterialRanges.from_dict(dict(ranges), where)
    raise ConfigError(f"{where}.ranges must be a mapping of categories, got {ranges!r}")


def checked_categories(where: str, categories) -> tuple[str, ...]:
    """A params section's ``categories`` as a tuple of lower-case names of :data:`CATEGORIES`,
    none twice and at least one; the one check ``materials``, ``eval`` and ``train.synthesis``
    share, messages naming ``where.categories``."""
    if isinstance(categories, str) or not isinstance(categories, (list, tuple)):
        raise ConfigError(f"{where}.categories must be a list of category names, got {categories!r}")
    cats = tuple(str(c).lower() for c in categories)
    if not cats:
        raise ConfigError(f"{where}.categories is empty")
    for c in cats:
        if c not in CATEGORIES:
            raise ConfigError(f"{where}.categories: unknown category {c!r} (choose from {', '.join(CATEGORIES)})")
    if len(set(cats)) != len(cats):
        raise ConfigError(f"{where}.categories has duplicates: {list(cats)}")
    return cats
