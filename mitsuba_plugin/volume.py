"""The ``lazy_solid_volume`` Mitsuba volume: a ``lazy_solid`` texture seen as a volume.

A heterogeneous medium reads its ``albedo`` (and ``sigma_t``) from volumes. Mitsuba's own
texture-to-volume conversion evaluates a texture at p = 0 only, so a solid texture needs
this wrapper, which queries the texture at the medium interaction's position::

    <medium type="heterogeneous">
        <volume type="lazy_solid_volume" name="albedo">
            <texture type="lazy_solid" name="texture"> ... </texture>
        </volume>
    </medium>
"""

from __future__ import annotations

import mitsuba as mi

from mitsuba_plugin.texture import fail

PLUGIN = "lazy_solid_volume"


class LazySolidVolume(mi.Volume):
    """The RGB of a nested ``lazy_solid`` texture at each medium point."""

    def __init__(self, props: mi.Properties) -> None:
        super().__init__(props)
        texture = props.get("texture", None)
        if texture is None or not hasattr(texture, "colors_at"):
            raise fail(PLUGIN, "texture", 'must be a nested texture of type "lazy_solid"')
        self.texture = texture
        self._max = texture.max()

    def eval(self, it: mi.Interaction3f, active: mi.Bool = True) -> mi.UnpolarizedSpectrum:
        return self.texture.colors_at(it, active)

    def eval_3(self, it: mi.Interaction3f, active: mi.Bool = True) -> mi.Vector3f:
        return mi.Vector3f(self.texture.colors_at(it, active))

    def eval_1(self, it: mi.Interaction3f, active: mi.Bool = True) -> mi.Float:
        return mi.luminance(self.texture.colors_at(it, active))

    def max(self) -> float:
        return self._max

    def channel_count(self) -> int:
        return 3

    def traverse(self, callback: mi.TraversalCallback) -> None:
        callback.put("texture", self.texture, mi.ParamFlags.NonDifferentiable)

    def to_string(self) -> str:
        return f"LazySolidVolume[texture={self.texture.to_string()}]"

MEDIUM = "lazy_solid_medium"


def lazy_solid_medium(props: mi.Properties) -> mi.Medium:
    """A ``heterogeneous`` medium whose albedo is a nested ``lazy_solid`` texture."""
    volume = mi.Properties()
    volume["texture"] = props["albedo"]
    return mi.load_dict({"type": "heterogeneous", "albedo": LazySolidVolume(volume),
                         "sigma_t": props.get("sigma_t", 1.0), "scale": props.get("scale", 1.0)})
