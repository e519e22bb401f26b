"""The settings of the per-pixel generator's effects (:class:`Effects`: each effect's
strength, off at 0) and the laws' constants, without torch: the train stage's parameters
read the effect names from here (:data:`EFFECT_NAMES`), and the steps that apply them are
:mod:`cnnps.synth.pixel_effects`.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

from cnnps.infra.errors import ConfigError


SATURATION_RANGE = (1.0, 4.0)  # a saturated pixel's brightest observation lands at k x clip, k log-uniform here


EXPOSURE_RANGE = (1.0 / 64.0, 0.5)  # an unsaturated quantised pixel's brightest lands at k x full scale


BLACK_LEVEL_MAX = 2.0 / 255.0  # black-level offset U(-max, max) of full scale per quantised pixel


EIGHT_BIT_SHARE = 0.5  # share of quantised pixels stored in 8 bits (255 levels); the rest 16 bits (65535)


MIX_ALPHA_RANGE = (0.5, 1.0)  # foreground weight of a pixel straddling a depth discontinuity


FD90_RANGE = (0.3, 1.0)  # Burley's grazing factor fd90 of a pixel whose diffuse falls off, uniform here


@dataclass(frozen=True)
class Effects:
    """Global effects and capture realism, each off at 0 (probabilities and strengths in [0, 1];
    the two shares are on at 1, every pixel).

    - ``cast_shadow``: probability that a pixel has an occluder: a spherical cap of
      directions (axis at a random azimuth, elevation U(0°, 45°), half-angle U(20°, 60°))
      whose lights reach the pixel only through the ambient and indirect terms;
    - ``interreflection``: light bounced off a nearby lit surface of a random colour
      (random normal facing the pixel's hemisphere, RGB albedo ρ_n ~ U(0, 1)^3): per pixel
      r ~ U(0, interreflection) and indirect value r · ρ_pixel · ρ_n · max(0, n_n · l) per
      channel (ρ_pixel the pixel's diffuse, or for metals its base, colour); grey maps
      take the mean over R, G, B of this coloured term, RGB maps keep it per channel;
    - ``ambient``: a ~ U(0, ambient) per pixel times the pixel's brightest chosen value,
      added to every light (as :func:`cnnps.synth.training_samples.add_ambient`);
    - ``intensity_error``: per batch and light factor max(1 + N(0, σ), 0)
      (:func:`cnnps.synth.training_samples.light_gains`' law);
    - ``noise``: read and shot noise with per-pixel levels U(0, noise)
      (:func:`cnnps.synth.training_samples.add_noise`'s law), clipped at 0;
    - ``saturation``: probability that a pixel is over-exposed: its values are multiplied
      by an exposure that puts its brightest chosen value at k times the clip level 1,
      k log-uniform in :data:`SATURATION_RANGE`, and clipped at 1 (each channel in RGB);
    - ``quantisation``: probability that a pixel is stored as an integer image: an
      exposure puts its brightest chosen value at k of full scale (k as for
      ``saturation`` when the pixel is saturated, else log-uniform in
      :data:`EXPOSURE_RANGE`), a black-level offset U(-:data:`BLACK_LEVEL_MAX`,
      :data:`BLACK_LEVEL_MAX`) is added, values are clamped to [0, 1] and rounded to
      8 bits (1/255 steps, share :data:`EIGHT_BIT_SHARE`) or 16 bits (1/65535);
    - ``boundary_mix``: probability that a pixel straddles a depth discontinuity: its
      direct shading is alpha · (its own surface) + (1 − alpha) · (a second surface with
      an independently drawn normal and material), alpha ~ U(:data:`MIX_ALPHA_RANGE`);
      the target normal stays the first (foreground) surface's;
    - ``interreflection_share`` and ``ambient_share``: the probability that a pixel gets
      the inter-reflection, or the ambient term, at all (1: every pixel, as the two
      strengths alone mean); a real object's convex parts see neither, and every pixel
      lifted by them teaches the network maps no convex pixel shows;
    - ``grazing_falloff``: probability that a pixel's diffuse darkens toward grazing light
      as real matte surfaces do (DiLiGenT's BALL): Lambert's lobe times
      1 + (fd90 − 1)(1 − n·l)^5, fd90 ~ U(:data:`FD90_RANGE`) per pixel (``shade``'s
      ``fd90``; needs ``diffuse_model="lambert"``).

    Example: ``Effects(cast_shadow=0.3, saturation=0.1, quantisation=0.5, boundary_mix=0.05)``;
    ``Effects(interreflection=0.3, interreflection_share=0.3, grazing_falloff=0.3)``.
    """

    cast_shadow: float = 0.0
    interreflection: float = 0.0
    ambient: float = 0.0
    intensity_error: float = 0.0
    noise: float = 0.0
    saturation: float = 0.0
    quantisation: float = 0.0
    boundary_mix: float = 0.0
    interreflection_share: float = 1.0
    ambient_share: float = 1.0
    grazing_falloff: float = 0.0

    def __post_init__(self):
        for name in EFFECT_NAMES:
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and 0.0 <= v <= 1.0):
                raise ConfigError(f"pixelwise effect {name} must be in [0, 1], got {v!r}")

    @property
    def camera(self) -> bool:
        """True when a pixel may be exposed, clipped or quantised."""
        return bool(self.saturation or self.quantisation)

    @property
    def per_pixel_draws(self) -> bool:
        """True when the shares or the grazing falloff need draws of their own."""
        return self.interreflection_share < 1.0 or self.ambient_share < 1.0 or self.grazing_falloff > 0.0


EFFECT_NAMES = tuple(f.name for f in fields(Effects))  # the fields of Effects, in order: the effect names
