"""Independent ground truth for scene transmittance and images, with Mitsuba 3.

Transmittance from the light to a receiver ``x`` along the light path
``r(s) = o + s d``, ``0 <= s <= L`` (``o`` on the light side, ``|d| = 1``)::

    T(x) = exp(-int_0^L sigma_t(r(s)) ds)                       density grid
         * prod_p exp(-sigma_p * |chord_p cap [0, L]|)            particles
         * prod_c f_c                                              hair crossings
         * [no opaque blocker meets (0, L)]                        blockers

Modules: :mod:`.media` (the grid as a Mitsuba medium; :func:`sample_density`, the NumPy
statement of its convention), :mod:`.content` (light paths; particles, hair and blockers),
:mod:`.tracking` (the grid term by ratio tracking or ray march; :func:`transmittance`),
:mod:`.images` (cameras; :func:`render_reference`).  Mitsuba is imported, and its variant chosen
(:func:`mitsuba`), inside each call, never at import time.
"""
from .content import EPS_REL, MAX_CHUNK, blocked, light_paths
from .images import (PLANE_OFFSET, camera_rays, check_camera, default_camera, receiver_plane_for, render_reference)
from .media import mitsuba, mitsuba_volume, sample_density
from .tracking import MAX_LANES, MAX_SAMPLES, METHODS, raymarch_optical_depth, transmittance

__all__ = [
    "transmittance", "render_reference", "raymarch_optical_depth", "sample_density",
    "light_paths", "blocked", "mitsuba", "mitsuba_volume",
    "default_camera", "check_camera", "camera_rays", "receiver_plane_for",
    "METHODS", "MAX_LANES", "MAX_SAMPLES", "MAX_CHUNK", "EPS_REL", "PLANE_OFFSET"]
