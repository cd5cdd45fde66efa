"""Whether a scan's object goes on beyond the reconstructed box along the rotation axis.

The detector's first and last rows see the box's ends. Where they see the object (line integrals
above the noise-aware air threshold, ``datamanagers.ct.noise_air_threshold``) in most views, the
object continues beyond the box along the axis (a leg, a spine), and every method, classical or
neural, puts the attenuation of what lies outside into the box's end slices. Measured in the 68th
stop on the held-out ``knee-long`` (the knee with the leg 130 mm longer than the box at both ends):
its first and last rows see the object in 47 % of their pixels in every view, against at most 2 %
(noise) on the thirteen other scans; ASD-POCS's end slices reach 22.8 /m where the leg's most is
0.86, and k-neas ends at 12.7 dB over the whole box, 31.7 dB eight slices or more from its ends.

What every run does about it (:func:`fitting_scene`): the views are fitted on a box made longer at
both ends (:func:`axial_margin` slices each, as far as any ray that crosses the box's side walls
reaches along the axis, within the fields' domain ``|z| <= 1`` model unit), so that what lies
beyond the box has somewhere to go; the run's volume, metrics and meshes stay on the scene's own
box (:meth:`FittingBox.crop`). The longer box keeps the scene's model units (``Geometry.scale``),
so a model fitted on it is queried on the scene's voxel centres as it is.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

# a row sees the object where at least this share of its pixels is above the air threshold
ROW_OBJECT_SHARE = 0.1
# a scan is truncated along the axis where its first or last row sees the object in this share of the views
TRUNCATED_VIEW_SHARE = 0.5


def _sees_object(lines, air_threshold: float) -> np.ndarray:
    """``[N, L]``, one detector row or column per view -> ``[N]`` bool: it sees the object
    (``ROW_OBJECT_SHARE`` of its pixels above ``air_threshold``)."""
    return (lines > air_threshold).mean(axis=1) >= ROW_OBJECT_SHARE


def axial_truncation(projections, air_threshold: float) -> float:
    """``[N, nV, nU]`` line integrals (rows along the rotation axis) -> the share of views whose
    first or last detector row sees the object (``ROW_OBJECT_SHARE`` of its pixels above
    ``air_threshold``)."""
    p = np.asarray(projections)
    return float(np.mean(_sees_object(p[:, 0, :], air_threshold) | _sees_object(p[:, -1, :], air_threshold)))


def truncation_warning(scene, air_threshold: float | None = None) -> str | None:
    """One line for the user when ``scene``'s object goes on beyond its box along the axis, else None;
    ``air_threshold``: the training projections' noise-aware one where the caller has it already."""
    from ..datamanagers.ct import noise_air_threshold

    p = np.asarray(scene.train.projections)
    share = axial_truncation(p, noise_air_threshold(p)[0] if air_threshold is None else air_threshold)
    if share < TRUNCATED_VIEW_SHARE:
        return None
    return (f"the object reaches the detector's first or last row in {round(share * len(p))} of {len(p)} training views: it goes on "
            "beyond the reconstructed box along the rotation axis")


def lateral_truncation(projections, air_threshold: float, off_u: float = 0.0) -> float:
    """``[N, nV, nU]`` line integrals -> the share of views whose outer detector column sees the object
    (``ROW_OBJECT_SHARE`` of its pixels above ``air_threshold``): both end columns of a centred
    detector (``off_u`` 0), the one farther from the central ray of an offset (half-fan) one, whose
    shorter side crosses the object by design."""
    p = np.asarray(projections)
    first, last = _sees_object(p[:, :, 0], air_threshold), _sees_object(p[:, :, -1], air_threshold)
    outer = last if off_u > 0 else first if off_u < 0 else first | last
    return float(np.mean(outer))


def lateral_truncation_warning(scene, air_threshold: float | None = None) -> str | None:
    """One line for the user when ``scene``'s object is wider than the detector's field of view
    (:func:`lateral_truncation` in ``TRUNCATED_VIEW_SHARE`` of the views), else None."""
    from ..datamanagers.ct import noise_air_threshold

    p = np.asarray(scene.train.projections)
    threshold = noise_air_threshold(p)[0] if air_threshold is None else air_threshold
    share = lateral_truncation(p, threshold, scene.geometry.off_detector[0])
    if share < TRUNCATED_VIEW_SHARE:
        return None
    return (f"the object reaches the detector's outer column in {round(share * len(p))} of {len(p)} training views: it is wider "
            "than the field of view, so every view misses part of it; every method biases the volume near the field of view's "
            "edge and cannot reconstruct what lies outside it; a neural run keeps its classical start's values there, so its "
            "ASD-POCS start is run to 40 iterations instead of 10 (unless --reconstruction.iterations is given); an ASD-POCS run "
            "can be run further with --reconstruction.iterations 40")


def axial_margin(geometry, reach: float = 1.0) -> int:
    """Slices to add at each end of ``geometry``'s box so that it holds every ray's stretch inside
    the box's side walls: the cylinder about the axis through the box's farthest corner in x, y.
    A cone-beam ray through the pixel centres of detector row height ``v`` is at ``|z| = |v| t / DSD`` at ``t`` along the
    central axis, and ``t <= DSO + r`` inside that cylinder of radius ``r``; a parallel-beam ray
    keeps its ``|v|``. Capped so that the longer box ends within ``|z| <= reach`` (model units,
    the fields' domain); 0 where the box already reaches that far."""
    (_, nv), (_, dv), (_, ov) = geometry.n_detector, geometry.d_detector, geometry.off_detector
    v_most = (nv - 1) * dv / 2 + abs(ov)  # the outermost rows' pixel centres, where the rays are cast
    if geometry.mode == "cone":
        sx, sy = (n * d for n, d in zip(geometry.n_voxel[:2], geometry.d_voxel[:2]))
        ox, oy = geometry.off_origin[:2]
        r = max(math.hypot(ox + a * sx / 2, oy + b * sy / 2) for a in (-1, 1) for b in (-1, 1))
        z_most = v_most * (geometry.dso + r) / geometry.dsd
    else:
        z_most = v_most
    dz, oz = geometry.d_voxel[2], geometry.off_origin[2]
    half = geometry.n_voxel[2] * dz / 2
    room = reach - (abs(oz) + half)  # the fields' domain beyond the box's farther end
    wanted = max(z_most - oz - half, z_most + oz - half)  # the rays' reach beyond either end
    return max(0, min(math.ceil(wanted / dz - 1e-9), math.floor(room / dz + 1e-9)))


@dataclass(frozen=True)
class FittingBox:
    """The scene whose training views a run fits (``scene``), the slices its box has more than
    the scene's own at each end (``slices``; 0: the scene itself), and whether the object is wider
    than the detector's field of view (``wider_than_view``: nothing about the box changes for it, a
    neural run's classical start is run further, ``engine.classical_volume.start_options``)."""

    scene: object
    slices: int = 0
    wider_than_view: bool = False  # the object is wider than the detector's field of view (lateral_truncation_warning)

    def crop(self, volume):
        """A volume ``[nx, ny, nz + 2 slices]`` on the fitting box -> ``[nx, ny, nz]`` on the scene's box."""
        return volume if self.slices == 0 else volume[..., self.slices:-self.slices]


def extend_axially(scene, slices: int):
    """``scene`` with its box ``slices`` voxels longer at each end along the axis (same model
    units, voxel size and centre; the views unchanged); no ground truth (it holds only the box)."""
    g = scene.geometry
    geometry = replace(g, n_voxel=(g.n_voxel[0], g.n_voxel[1], g.n_voxel[2] + 2 * int(slices)))
    return replace(scene, geometry=geometry, image=None, labels=None, membership=None)


def fitting_scene(scene, air_threshold: float | None = None, say=None) -> FittingBox:
    """The box a run fits ``scene``'s views on: the scene's own, or where its object goes on beyond
    the box along the axis (:func:`truncation_warning`), one :func:`axial_margin` longer at each end.
    ``say`` gets the one-line warning and what is done about it, and a line where the object is
    wider than the detector's field of view (:func:`lateral_truncation_warning`; the box is kept,
    ``wider_than_view`` is set)."""
    if air_threshold is None:
        from ..datamanagers.ct import noise_air_threshold

        air_threshold = noise_air_threshold(np.asarray(scene.train.projections))[0]
    wide = lateral_truncation_warning(scene, air_threshold)
    if wide is not None and say is not None:
        say(f"[yellow]warning:[/yellow] {wide}")
    warning = truncation_warning(scene, air_threshold)
    if warning is None:
        return FittingBox(scene, wider_than_view=wide is not None)
    slices = axial_margin(scene.geometry)
    if say is not None:
        mm = slices * scene.geometry.d_voxel[2] * scene.geometry.mm_per_unit
        done = (f"the views are fitted on a box {slices} slices ({mm:.0f} mm) longer at each end, where the rays reach, and the "
                "volume is kept on the scene's box; the slices nearest its ends are the least certain" if slices
                else "the box is not made longer (the rays reach no farther along the axis, or it fills the fields' domain): the "
                "slices nearest its ends hold what lies beyond")
        say(f"[yellow]warning:[/yellow] {warning}; {done}")
    return FittingBox(extend_axially(scene, slices) if slices else scene, slices, wider_than_view=wide is not None)
