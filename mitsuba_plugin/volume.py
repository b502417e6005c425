"""The ``lazy_solid_medium`` Mitsuba medium: a heterogeneous medium whose albedo, and
optionally extinction, is a ``lazy_solid`` texture.

Mitsuba's own texture-to-volume conversion evaluates a texture at p = 0 only, and Python
volumes cannot be registered as plugins, so this medium wraps its nested textures in a
volume that queries them at each medium interaction's position::

    <medium type="lazy_solid_medium" name="interior">
        <texture type="lazy_solid" name="albedo"> ... </texture>
        <float name="sigma_t" value="6"/>   <!-- optional, default 1; a colour, a volume
                                                 or another lazy_solid texture -->
        <float name="scale" value="1"/>     <!-- optional, default 1: multiplies sigma_t -->
        <boolean name="sample_emitters" value="true"/>  <!-- optional, as Mitsuba's media -->
        <phase type="hg"> ... </phase>      <!-- optional, default isotropic -->
    </medium>
"""

from __future__ import annotations

import math

import mitsuba as mi

from mitsuba_plugin.properties import (
    check_known,
    did_you_mean,
    get_property,
    property_error,
    unknown_property,
)
from mitsuba_plugin.spectrum import extinction_spectrum, luminance, spectrum

MEDIUM = "lazy_solid_medium"
# Mitsuba's heterogeneous medium exists only within its sigma_t volume's bounding box, the
# unit cube [0, 1]^3 unless the volume's to_world places it: the volumes made here span
# this far each way (world units), so that the medium fills the shape it is the inside of,
# as the unbounded texture does and as a homogeneous medium would: far past any scene
# float32 positions can hold (a unit apart at 1e7), while the box's float32 volume stays
# finite.
_REACH = 1e12
# Besides these, a nested phase function, which may go by any name (unnamed, the parser's
# "_arg_0"); "phase" is in _PROPERTIES for the typos of it.
_VALUES = ("albedo", "sigma_t", "scale", "sample_emitters")
_PROPERTIES = (*_VALUES, "phase")


class LazySolidVolume(mi.Volume):
    """The color of a ``lazy_solid`` texture at each medium point, as the variant's
    spectrum (``eval``) or as RGB (``eval_3``): a reflectance for an albedo, an unbounded
    spectrum for an ``extinction`` (:func:`~mitsuba_plugin.spectrum.extinction_spectrum`)."""

    def __init__(self, texture: mi.Texture, extinction: bool = False) -> None:
        props = mi.Properties()
        props["to_world"] = _everywhere()
        super().__init__(props)
        self.texture = texture
        self._upsampled = extinction_spectrum if extinction else spectrum
        # The medium's majorant: an extinction's spectrum stays below twice its largest
        # channel, as Mitsuba's gridvolume bounds its own.
        self._max = 2.0 * texture.largest if extinction and mi.is_spectral else texture.max()

    def eval(self, it: mi.Interaction3f, active: mi.Bool = True) -> mi.UnpolarizedSpectrum:
        return self._upsampled(self.texture.colors_at(it, active), it.wavelengths)

    def eval_3(self, it: mi.Interaction3f, active: mi.Bool = True) -> mi.Vector3f:
        return mi.Vector3f(self.texture.colors_at(it, active))

    def eval_1(self, it: mi.Interaction3f, active: mi.Bool = True) -> mi.Float:
        return luminance(self.texture.colors_at(it, active))

    def max(self) -> float:
        return self._max

    def channel_count(self) -> int:
        return 3

    def traverse(self, callback: mi.TraversalCallback) -> None:
        callback.put("texture", self.texture, mi.ParamFlags.NonDifferentiable)

    def to_string(self) -> str:
        return f"LazySolidVolume[texture={self.texture.to_string()}]"


def _everywhere() -> mi.ScalarTransform4f:
    """The unit cube made the cube of +-_REACH."""
    return (mi.ScalarTransform4f().translate([-_REACH] * 3)
            @ mi.ScalarTransform4f().scale(2 * _REACH))


def _check_world_space(name: str, texture: mi.Texture) -> None:
    """Refuse an object-space texture: a medium's points belong to no shape, so it would be
    read in world space, not follow the shape as asked."""
    if texture.space == "object":
        raise property_error(MEDIUM, name, 'is a lazy_solid of space="object", which a medium '
                             "cannot follow (its points belong to no shape): place it with "
                             "to_world in world space")


def lazy_solid_medium(props: mi.Properties,
                      volume_type: type[LazySolidVolume] = LazySolidVolume) -> mi.Medium:
    """A ``heterogeneous`` medium whose albedo is a nested ``lazy_solid`` texture, as may
    be its ``sigma_t``.

    ``volume_type`` is bound when the module is (re)loaded for a variant: a later reload
    for another variant rebinds the module's ``LazySolidVolume``, not this default.
    """
    nested = [name for name in props if name not in _VALUES
              and props.type(name) == mi.Properties.Type.Object]
    check_known([name for name in props if name not in nested], _PROPERTIES, MEDIUM)
    if "phase" in props and "phase" not in nested:  # <string name="phase" value="hg"/>
        raise property_error(MEDIUM, "phase", "must be a nested phase function (<phase ...>), "
                             f"got {props['phase']!r}")
    for name in nested:
        if not isinstance(props[name], mi.PhaseFunction):
            if did_you_mean(name, _VALUES):  # a misspelt albedo, say
                raise unknown_property(MEDIUM, name, _VALUES)
            raise property_error(MEDIUM, name, "must be a nested phase function (<phase ...>)")
    albedo = props.get("albedo", None)
    if albedo is None or not hasattr(albedo, "colors_at"):
        raise property_error(MEDIUM, "albedo", 'must be a nested texture of type "lazy_solid"')
    _check_world_space("albedo", albedo)
    sigma_t = props.get("sigma_t", 1.0)
    if hasattr(sigma_t, "colors_at"):  # a lazy_solid: read at each point, as the albedo
        _check_world_space("sigma_t", sigma_t)
        if sigma_t.lowest < 0:
            raise property_error(MEDIUM, "sigma_t", "is a lazy_solid whose exemplar holds "
                                 f"negative values (down to {sigma_t.lowest:.3g}); an "
                                 "extinction is never negative")
        sigma_t = volume_type(sigma_t, extinction=True)
    elif isinstance(sigma_t, int | float) and not isinstance(sigma_t, bool):
        sigma_t = float(sigma_t)  # as Mitsuba's own media take an <integer> too
        if not (math.isfinite(sigma_t) and sigma_t >= 0):
            raise property_error(MEDIUM, "sigma_t",
                                 f"must be finite and not negative, got {sigma_t}")
    elif isinstance(sigma_t, mi.Texture) and sigma_t.is_spatially_varying():
        kind = str(sigma_t).split("[", 1)[0]
        raise property_error(MEDIUM, "sigma_t", f"is a {kind} texture, which Mitsuba's media "
                             "read at one point only: give a lazy_solid texture, a <float ...>, "
                             "a colour or a nested volume")
    elif "sigma_t" in props and props.type("sigma_t") == mi.Properties.Type.Color:
        # As Mitsuba's media take an <rgb>: a reflectance-like colour, scale multiplying it.
        rgb = [float(c) for c in sigma_t]
        if not all(math.isfinite(c) and 0 <= c <= 1 for c in rgb):
            raise property_error(MEDIUM, "sigma_t", "must be a colour of channels within "
                                 "[0, 1], as Mitsuba's media take one (scale multiplies it), "
                                 f"got {', '.join(f'{c:g}' for c in rgb)}")
    elif isinstance(sigma_t, str | bool):  # spectra and volumes Mitsuba checks
        raise property_error(MEDIUM, "sigma_t", f"must be a <float ...>, a colour or a nested "
                             f"volume, got {sigma_t!r}")
    scale = get_property(props, "scale", float, 1.0, MEDIUM)
    if not (math.isfinite(scale) and scale >= 0):
        raise property_error(MEDIUM, "scale", f"must be finite and not negative, got {scale}")
    if not isinstance(sigma_t, mi.Volume):  # a number or a colour: everywhere, as textures
        sigma_t = mi.load_dict({"type": "constvolume", "value": sigma_t,
                                "to_world": _everywhere()})
    medium = {"type": "heterogeneous", "albedo": volume_type(albedo), "sigma_t": sigma_t,
              "scale": scale,
              "sample_emitters": get_property(props, "sample_emitters", bool, True, MEDIUM)}
    if len(nested) > 1:
        raise property_error(MEDIUM, "phase", f"must be given once, got {len(nested)}")
    if nested:
        medium["phase"] = props[nested[0]]
    return mi.load_dict(medium)
