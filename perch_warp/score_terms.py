"""What a candidate's score is made of: named scores and their terms (issue 17).

A feature point's value is

    value = cos(R, I) * gain - offset          (kernel #2, kernels/features.py)

with R the candidate's conv1 feature there, I the photo's, `gain` the photo's rarity
(thesis §3.2.2) and `offset` the credit the background alone would earn there; a
candidate's score is sum(top k values) / (k + shrink), k = ceil(α n) of its n
silhouette points (kernels/reduce.py). `thesis` is the thesis's formula exactly
(offset 0, shrink 0, windows composited onto the photo).

Terms (each off in `thesis`):
- ``surround``: what an edge window sees beyond the silhouette. ``photo`` (thesis):
  the photo's pixels, so a silhouette that touches a strong edge borrows it; ``fill``:
  the weights' preprocessing mean (zero input to conv1), so only the render counts; ``weighted``:
  the photo, with the cosine weighted by the share of the window the silhouette covers (an edge
  window still checks the outline, but cannot borrow a match from the photo's own pixels).
- ``background`` λ: offset = λ * gain * max(0, cos(B, I)), B the photo's commonest
  appearance (the centroid of its largest k-means cluster, usually the table): a
  point earns only what the render explains better than the table would.
- ``shrink`` k0: the top-α sum over k + k0 points, so a small silhouette's mean of
  few points, whose maximum over many candidates is inflated by chance, is shrunk
  towards 0 (a size-aware statistic).
- ``rarity``: ``max`` (thesis: 1 - count / max count; the commonest cluster weighs 0)
  or ``total`` (1 - count / all points); ``inits``: k-means initialisations (best of).
- ``cluster``: what k-means clusters for the rarity. ``features`` (thesis): conv1's features as they
  are. Under a hard light the commonest cluster is "dark" (cast shadows, a dim wall) and takes in
  the face of an object turned from the light, which then weighs 0 however distinctive its print.
  ``direction``: the direction of conv1's response without its bias, (F - b) / |F - b| with
  F - b = W x linear in the window x, so a window and the same window darker or brighter by a
  factor fall in one cluster: the rarity says how common an appearance is, not how lit
  (perch_warp.rarity.unit_responses). Only the weights change, each still in [0, 1), so the bound
  holds as it is. Raw conv1 only (not `--relu`).
- ``outline`` w: the outline term (issue 17 (d), perch_warp.outline): a point on the
  candidate's outline also earns w * |e . n|, the photo's normalised intensity gradient across
  the rendered outline's normal, so a silhouette that follows the photo's edges gains over a
  look-alike patch whose edges run elsewhere.
- ``table`` w: the footing term (issue 17 (i), perch_warp.footing): w times how much the
  table plane just in front of the candidate's footprint looks like the photo's commonest
  appearance (the table), so a candidate standing on a wall, a monitor or another object's
  top, where the table plane is hidden, loses to one standing on the table. It depends on the
  place alone, so it is added to the bound as it is.
- ``texture``: how the render reads the mesh's texture (issue 17 (f)). ``bilinear`` (thesis):
  one lookup per pixel ray, which aliases where a pixel covers many texels (a 2048² texture on
  a 10 cm object at 0.8 m); ``mip``: mip-mapped lookups, each hit read from a copy of the texture
  averaged to the pixel's footprint there (perch_warp.mipmap), as a camera pixel averages. Only
  colours change, not the silhouette, so the bound holds as it is.
- ``light`` γ: photometric invariance (issue 17 (c)). conv1 with the preprocessing's mean
  subtracted and its bias is not invariant to brightness: a flat yellow patch at 60 % of its
  brightness gives a feature pointing elsewhere, so a shadowed target loses to a lit look-alike.
  With γ > 0 every window, the photo's and the candidate's, is scaled by (ref / max(L, 0.1))^γ
  before conv1, L its mean brightness and ref the preprocessing mean's (kernels/features.py
  `Exposure`): γ = 1 reads every window at the same brightness, keeping its colour and texture.
  The photo's features change with it, so its rarity (k-means) does too; the cosine stays <= 1,
  so the bound holds as it is.
- ``rectified`` b: raw and rectified conv1 together (a lead of the stop-33 screen: raw conv1 and
  AlexNet's ReLU after it lose different targets). A point's cosine is (1 - b) cos(R, I) +
  b cos(R+, I+), R+ = max(R, 0) and I+ = max(I, 0) per channel (0 where either vanishes, as for
  cos); the photo's rarity stays the raw features'. The ReLU keeps only the channels a window
  excites, so two windows that agree in what they lack (both dark, both without a red edge) no
  longer agree for it. A convex blend of two numbers <= 1 is <= 1, so the bound holds as it is.
  It needs raw conv1 (not `--relu`, whose features are already rectified).
- ``exposure`` e: the render read brighter or darker (issue 17 (c), a per-candidate gain). The
  render is the texture's albedo, the photo what a camera's exposure and the scene's light made of
  it: at the ground truth the photo's mean colour is 0.44 to 1.89 times the render's on the synthetic
  development set, and the misses crowd at the ends. With e > 0 a candidate is scored with its
  rendered pixels scaled by each gain g = 2^(k/2) within +-e stops (half-stop steps; the photo's
  pixels in an edge window stay as they are), and its score is the best of those top-α means: the
  whole silhouette at one gain, so no point picks its own (unlike ``light``, which rescales every
  window). conv1 is linear, so conv1(g render + rest) = g a + q with a the response to the rendered
  pixels alone and q the bias plus the rest's: one split convolution serves every gain. Every
  gain's value is a cosine times the rarity, so the bound holds as it is. Not with ``light``.
- ``tone`` e: the render read through a camera's exposure, highlights clipped (issue 17 (c)).
  Under a strong light a camera burns a lit face out to white and the texture's print vanishes
  from it (the synthetic development set's harsh light: a median 18 % of a target's visible pixels
  are 255 in some channel, 68 % of one gelatin box's; under normal light a median 0 %), which no
  gain of the unclipped ``exposure`` term reproduces, since
  conv1 is linear and a cosine ignores scale. With e > 0 (whole stops, up to MAX_TONE) a candidate
  is also scored with every rendered colour c read as srgb(min(1, 2^k lin(c))) for k = 1 .. e
  (lin, srgb: the sRGB transfer functions; the photo's pixels in an edge window stay as they
  are), and its score is the best of those top-α means, k = 0 (the render as it is) included:
  the whole silhouette at one exposure, as with ``exposure``. Clipping is not linear, so each
  exposure is convolved on its own (e + 1 times the features). Every value is still a cosine
  times the rarity, so the bound holds as it is. Not with ``exposure`` or ``light``.
- ``smooth`` σ: conv1's filters low-passed (a Gaussian of σ pixels, perch_warp.features.smoothed), for
  the photo's features and the candidates' alike: conv1 then reads every window as if blurred, so a
  photo's pixel noise (the synthetic set's harsh light leaves speckle on lit objects) and texture
  finer than the camera resolves, which the render has and the photo lacks, move neither. The
  weights change, not the formula, so the bound holds as it is.
- ``shade`` s: the render lit from above the table (issue 17 (c)). The thesis's render has one
  colour per texel, the photo's faces are as bright as the light makes them: under the synthetic
  set's harsh light a face turned to the light is burnt out while its neighbour is in shadow. With
  s > 0 (up to 1) kernel #1 scales each hit's linear light by 1 - s + s max(0, n . l), n the mesh's
  interpolated vertex normal and l the table's normal (kernels/render.py: Shading): the top lit as
  the texture, the sides darker as they turn away. Colours change, not the formula, so the bound
  holds as it is (nor does it depend on them); the render costs one normal blend per hit.
- ``centre`` c: the pattern inside the silhouette, not only its colours (a lead of stop 38's prototype,
  docs/accuracy.md). conv1's cosine on a target's large flat regions is mostly a colour match, so an
  object or a patch of the same colour scores like the target; what tells them apart is where the
  print is. With c > 0 a point's cosine is (1 - c) cos(R, I) + c cos(R - Rm, I - Im), Rm and Im the
  means of the candidate's conv1 features and of the photo's over its compared points (a first pass
  of kernel #2 sums them), so a colour or brightness offset common to the candidate cancels from the
  second cosine. A convex blend of two cosines is <= 1, so the bound holds as it is. Kernel #2's
  torch form only (`--conv auto` picks it for this term on a GPU too), raw conv1 (not `--relu`); with shift r the
  means are those of the undisplaced points. Not with exposure, tone, light or rectified.
- ``shift`` r: the grid stage's tolerance of a misaligned grid (issue 17 (g)). A grid pose
  is up to half a step from the truth, and a small textured object's score peak is narrower
  than that; so a grid candidate is scored against the photo displaced by every (dx, dy) of
  feature-grid cells with |dx|, |dy| <= r, and its score is the best of those (2r + 1)^2
  top-α means (the whole silhouette moves together: no point picks its own displacement).
  Only the grid is scored so: the refinement below the grid compares undisplaced
  (ScoringService.refining), so the answer's pose and score are the plain score's.

The pruned search stays exact for every score: cos <= 1 (a blend of two cosines with `rectified` or
`centre`) and gain >= 0 give
value <= gain - offset (+ w * the largest |e| within one stride of the point with the outline
term, perch_warp.outline) =: ceiling, pointwise on the silhouette, and the top-k sum is
monotone in every value with the same k and the same positive divisor, so the
top-α reduction of the ceiling bounds the score (perch_warp.bound). With shift r, displacement
d's value at point p is at most ceiling(p + d) (0 beyond the photo's grid, where the value is
0), so at most the ceiling max-pooled over the (2r + 1)^2 cells around p (zero-padded, since
ceiling >= 0): the top-α reduction of the pooled ceiling bounds every displacement's score,
hence their maximum (Photo.ceiling_within). The footing term (``table``) depends on the
candidate's place alone and is added, the same, to its score and to its bound.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from .errors import PerchError

SURROUNDS = ("photo", "fill", "weighted")
# How kernel #1 reads a texture: one bilinear lookup per pixel ray (the thesis's), or mip-mapped.
TEXTURES = ("bilinear", "mip")
RARITY_MODES = ("max", "total")
# What k-means clusters for the rarity: conv1's features as they are (the thesis's), or the direction of
# conv1's response without its bias (perch_warp.rarity.unit_responses), the same for a window darker or brighter.
CLUSTER_SPACES = ("features", "direction")
MAX_SHIFT = 3  # (2 r + 1)^2 = 49 comparisons per point at most
MAX_EXPOSURE = 2.0  # stops: 9 gains, 1/4 to 4
MAX_TONE = 3  # whole stops brighter: 4 exposures, 1 to 8
MAX_SMOOTH = 3.0  # pixels: wider and an 11 x 11 filter is little but its mean


@dataclass(frozen=True)
class ScoreTerms:
    """The terms of a score (see the module doc); the defaults are the thesis's."""

    surround: str = "photo"
    background: float = 0.0
    shrink: float = 0.0
    rarity: str = "max"
    inits: int = 1
    shift: int = 0
    outline: float = 0.0
    table: float = 0.0
    texture: str = "bilinear"
    light: float = 0.0
    rectified: float = 0.0
    exposure: float = 0.0
    tone: int = 0
    smooth: float = 0.0
    shade: float = 0.0
    centre: float = 0.0
    cluster: str = "features"

    def __post_init__(self) -> None:
        if self.cluster not in CLUSTER_SPACES:
            raise PerchError(f"score term cluster must be one of {', '.join(CLUSTER_SPACES)}, got {self.cluster!r}")
        if not (np.isfinite(self.centre) and 0.0 <= self.centre <= 1.0):
            raise PerchError(f"score term centre must be in [0, 1], got {self.centre}")
        if self.centre > 0.0 and (self.exposure > 0.0 or self.tone > 0 or self.light > 0.0 or self.rectified > 0.0):
            raise PerchError("score term centre cannot be combined with exposure, tone, light or rectified")
        if not (np.isfinite(self.shade) and 0.0 <= self.shade <= 1.0):
            raise PerchError(f"score term shade must be in [0, 1], got {self.shade}")
        if not (np.isfinite(self.smooth) and 0.0 <= self.smooth <= MAX_SMOOTH):
            raise PerchError(f"score term smooth must be 0 to {MAX_SMOOTH} pixels, got {self.smooth}")
        if not 0 <= self.tone <= MAX_TONE:
            raise PerchError(f"score term tone must be 0 to {MAX_TONE} whole stops, got {self.tone}")
        if self.tone > 0 and (self.exposure > 0.0 or self.light > 0.0):
            raise PerchError("score term tone cannot be combined with exposure or light: choose one")
        if not (np.isfinite(self.exposure) and 0.0 <= self.exposure <= MAX_EXPOSURE):
            raise PerchError(f"score term exposure must be 0 to {MAX_EXPOSURE} stops, got {self.exposure}")
        if not float(2.0 * self.exposure).is_integer():
            raise PerchError(f"score term exposure must be a whole number of half stops, got {self.exposure}")
        if self.exposure > 0.0 and self.light > 0.0:
            raise PerchError("score terms exposure and light cannot be combined: choose one")
        if not (np.isfinite(self.rectified) and 0.0 <= self.rectified <= 1.0):
            raise PerchError(f"score term rectified must be in [0, 1], got {self.rectified}")
        if not (np.isfinite(self.light) and 0.0 <= self.light <= 1.0):
            raise PerchError(f"score term light must be in [0, 1], got {self.light}")
        if self.texture not in TEXTURES:
            raise PerchError(f"score term texture must be one of {', '.join(TEXTURES)}, got {self.texture!r}")
        if self.surround not in SURROUNDS:
            raise PerchError(f"score term surround must be one of {', '.join(SURROUNDS)}, got {self.surround!r}")
        if self.rarity not in RARITY_MODES:
            raise PerchError(f"score term rarity must be one of {', '.join(RARITY_MODES)}, got {self.rarity!r}")
        if not (np.isfinite(self.background) and 0.0 <= self.background <= 1.0):
            raise PerchError(f"score term background must be in [0, 1], got {self.background}")
        if not (np.isfinite(self.shrink) and self.shrink >= 0.0):
            raise PerchError(f"score term shrink must be >= 0, got {self.shrink}")
        if not (np.isfinite(self.outline) and 0.0 <= self.outline <= 1.0):
            raise PerchError(f"score term outline must be in [0, 1], got {self.outline}")
        if not (np.isfinite(self.table) and 0.0 <= self.table <= 1.0):
            raise PerchError(f"score term table must be in [0, 1], got {self.table}")
        if self.inits < 1:
            raise PerchError(f"score term inits must be >= 1, got {self.inits}")
        if not 0 <= self.shift <= MAX_SHIFT:
            raise PerchError(f"score term shift must be 0 to {MAX_SHIFT} feature-grid cells, got {self.shift}")

    def raw_conv1_terms(self) -> list[str]:
        """The terms set here that read conv1's raw response, which `--relu` discards (the engine refuses
        them together): each as `key=value (why)`."""
        terms = []
        if self.rectified > 0.0:
            terms.append(f"rectified={self.rectified} (raw and rectified conv1 blended)")
        if self.cluster == "direction":
            terms.append("cluster=direction (k-means on the direction of conv1's response without its bias)")
        if self.centre > 0.0:
            terms.append(f"centre={self.centre} (each candidate's features centred)")
        return terms

    def below_grid(self) -> ScoreTerms:
        """The terms the refinement below the grid scores with: the same without the grid's shift."""
        return dataclasses.replace(self, shift=0)

    def describe(self) -> str:
        """`key=value,...` of the terms that differ from the thesis's (empty for the thesis)."""
        base = ScoreTerms()
        return ",".join(
            f"{f.name}={getattr(self, f.name)}"
            for f in dataclasses.fields(self)
            if getattr(self, f.name) != getattr(base, f.name)
        )

    def spec(self) -> str:
        """These terms as a --score value that parse_score reads back: describe(), or "thesis"."""
        return self.describe() or "thesis"


SCORES: dict[str, ScoreTerms] = {
    "thesis": ScoreTerms(),
    # The thesis's formula, its grid stage tolerant of a misaligned grid by one feature cell (issue 17
    # (g), chosen on the development set: docs/accuracy.md).
    "grid-tolerant": ScoreTerms(shift=1),
    # grid-tolerant, each point's cosine half the plain one and half the centred one (the pattern inside
    # the silhouette, not only its colours; chosen on the development set at stop 40: docs/accuracy.md).
    "centred": ScoreTerms(shift=1, centre=0.5),
    # centred, the photo's rarity taken from the best of four k-means starts (lowest inertia) rather
    # than one, so the weights depend less on one start's luck (chosen on the development set at stop
    # 45, adopted at stop 46: docs/accuracy.md).
    "centred-4starts": ScoreTerms(shift=1, centre=0.5, inits=4),
    # centred-4starts, the photo's rarity clustered on the direction of conv1's response without its bias,
    # so a window in shadow and the same window lit fall in one cluster and a face turned from a hard
    # light no longer weighs 0 as "dark" (chosen on the development set at stop 49's full-resolution
    # screen, adopted at stop 52: docs/accuracy.md).
    "centred-direction": ScoreTerms(shift=1, centre=0.5, inits=4, cluster="direction"),
}

# The frozen score (docs/accuracy.md): the default of the CLI, EngineConfig and bench alike.
DEFAULT_SCORE = "centred-direction"


def parse_score(spec: str) -> tuple[str, ScoreTerms]:
    """A score by name (SCORES) or as terms `key=value,...` over the thesis's (e.g.
    `surround=fill,shrink=16`); returns the name to report and the terms."""
    if spec in SCORES:
        return spec, SCORES[spec]
    if "=" not in spec:
        raise PerchError(
            f"unknown score {spec!r}: use one of {', '.join(SCORES)} or terms like surround=fill,shrink=16"
        )
    kinds = {f.name: f.type for f in dataclasses.fields(ScoreTerms)}
    values: dict = {}
    for part in spec.split(","):
        key, _, raw = part.partition("=")
        key = key.strip()
        if key not in kinds:
            raise PerchError(f"unknown score term {key!r} in {spec!r}: terms are {', '.join(kinds)}")
        kind = kinds[key]
        try:
            values[key] = float(raw) if kind == "float" else int(raw) if kind == "int" else raw.strip()
        except ValueError:
            raise PerchError(f"score term {key} needs a {kind}, got {raw!r}") from None
    terms = ScoreTerms(**values)
    return terms.spec(), terms


def exposure_gains(stops: float) -> np.ndarray:
    """The exposure term's gains (float32, 1 first): 2^(k / 2) for every half stop k / 2 within
    +-stops (stops 1: 1, 1/sqrt(2), sqrt(2), 1/2, 2); (1,) for 0."""
    n = int(round(2.0 * stops))
    ks = [0] + [k for j in range(1, n + 1) for k in (-j, j)]
    return np.array([2.0 ** (k / 2.0) for k in ks], dtype=np.float32)


def tone_gains(stops: int) -> np.ndarray:
    """The tone term's exposures (float32, 1 first): 2^k in linear light for k = 0 .. stops."""
    return np.array([2.0**k for k in range(int(stops) + 1)], dtype=np.float32)


def likeness_to_commonest(features: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """(N,) float64 max(0, cos(B, I)) for the photo's features I (N, C), with B the centroid of the
    largest cluster of labels (N,): how much each point looks like the photo's commonest appearance
    (usually the table). The background term's offset and the footing term (perch_warp.footing) read it."""
    f = np.asarray(features, np.float64)
    B = f[labels == int(np.argmax(np.bincount(labels)))].mean(axis=0)
    norms = np.linalg.norm(f, axis=1) * np.linalg.norm(B)
    cos = np.divide(f @ B, norms, out=np.zeros(len(f)), where=norms > 1e-12)
    return np.maximum(cos, 0.0)


def background_offset(features: np.ndarray, labels: np.ndarray, gain: np.ndarray, weight: float) -> np.ndarray:
    """offset (N,) = weight * gain * likeness_to_commonest(features, labels); zeros when weight is 0."""
    if weight == 0.0:
        return np.zeros(len(features), np.float32)
    return (weight * np.asarray(gain, np.float64) * likeness_to_commonest(features, labels)).astype(np.float32)
