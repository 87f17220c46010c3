"""``warp_gel``: a tactile simulator in NVIDIA Warp: a gel pressed with a constant force, shaded by the sensor's lights.

One call simulates a batch of touches of one object (a ``wp.Mesh`` built once per object) in a few kernel
launches, on the ``cpu`` or a ``cuda`` warp device with the same code:

1. **Height field.** From every pixel's point on the undeformed gel (``Sensor.gel_points``) a ray is cast along
   the sensor's axis (-z); ``t`` is the distance to the object. The sensor first touches the object after
   advancing ``t_min = min t``; the gap under each pixel is then ``g = t - t_min``. The rays are parallel, so
   for a rigid sensor pose the cast is done as an orthographic rasterisation of the mesh in the sensor frame
   (same hits, far cheaper than one BVH query per pixel); scaled poses use ``wp.mesh_query_ray``.
2. **Constant-force press.** After advancing a further ``d`` (the penetration), the contact area follows the
   method of dimensionality reduction for elastic contact: it is the area where ``g <= d / 2`` (exact for a
   paraboloid, Hertz ``a = sqrt(R d)``; exact for a flat punch). The normal force follows from the incremental
   stiffness of an elastic half-space, ``dF/dd = 2 E* a`` with ``a = sqrt(A / pi)``, stiffened for a thin layer
   of thickness ``h`` by ``1 + 1.33 (a/h) + 1.33 (a/h)^3`` (bonded thin-layer correction). ``F(d)`` is tabulated
   from a histogram of gaps and inverted for the target force: a sphere then obeys Hertz,
   ``F = 4/3 E* sqrt(R) d^1.5``.
3. **Deformation.** Where in contact the gel takes the object's shape (indentation ``u = d - g``). Around the
   contact the surface falls off smoothly: a screened membrane equation ``lap(u) = u / lambda^2`` (``lambda`` a
   multiple of the gel thickness) relaxed on a coarse grid with the contact as a constraint, upsampled with
   cubic B-splines.
4. **Shading.** Normals of the deformed surface, lit by the sensor's coloured point lights (diffuse + specular,
   ``Sensor.shade``); the difference to the undeformed gel's shading is blurred and added to the sensor's
   background, then Gaussian noise (drawn from a unit-variance table of normal quantiles). With no contact the
   image is the background plus noise.

A calibrated sensor (``sensor.calibration``, written by ``tnf calibrate``) replaces step 4's lights with its
measured shading table (colour change by surface slope), and brings its own blur, noise, background and the
gel's fall-off length. ``press_heights(..., penetration=d)`` presses to a given depth instead of a force, as
calibration presses are given.

Outputs (``TouchBatch``): 8-bit RGB images, indentation maps (metres), contact masks, the achieved force (N),
the penetration ``d`` (m), the first-contact point and the sensor pose at contact.

The package, one module a step: ``raycast`` (1), ``contact`` (2), ``deformation`` (3), ``shading`` (4, with blur
and noise); ``simulator`` holds ``WarpGel``, which launches them.
"""

from tnf.sim.warp_gel.simulator import WarpGel

__all__ = ["WarpGel"]
