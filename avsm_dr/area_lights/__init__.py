"""Area-light volumetric shadows: imperfect voxelized shadow volumes.

Wyman and Dai, "Imperfect Voxelized Shadow Volumes": an area light in a homogeneous
single-scattering medium is sampled as K virtual point lights (VPLs); each VPL gets a
coarse, partially incorrect (imperfect) visibility volume, all packed into one buffer,
extruded into shadow volumes by one parallel scan along light rays, and the in-scattered
light is gathered along camera rays by a Riemann sum that interpolates only at shadow
boundaries.

Example::

    from avsm_dr import area_lights as al
    scene = al.default_scene(64, 64)
    out = al.render(scene, "imperfect", vpls=64, resolution=128)
    out.image, out.timings          # (H, W) radiance; seconds per phase
    ref, err = al.render_mitsuba(scene, spp=1024)   # Mitsuba volpath ground truth

Modules: :mod:`.area_scene`, :mod:`.vpl`, :mod:`.geometry`, :mod:`.visibility`, :mod:`.gather`,
:mod:`.methods` (the three methods, timings), :mod:`.reference` (Mitsuba ground truth).
"""
from .methods import INTERPOLATIONS, METHODS, AreaLightRender, render
from .area_scene import AreaLightScene, Box, Medium, PinholeCamera, QuadLight, Sphere, default_scene
from .reference import render_mitsuba
from .vpl import LightGrid, fit_grid, sample_vpls

__all__ = [
    "AreaLightScene", "Box", "PinholeCamera", "Medium", "QuadLight", "Sphere", "default_scene",
    "render", "AreaLightRender", "METHODS", "INTERPOLATIONS", "render_mitsuba",
    "LightGrid", "fit_grid", "sample_vpls"]
