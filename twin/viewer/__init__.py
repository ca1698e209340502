"""Live 3D view of reconstructed catheter shapes in a browser, showing the error against the truth.

:class:`Viewer` starts the scene server (:mod:`twin.viewer.server`, ``python -m twin.viewer.server``) on
127.0.0.1 — open the printed URL — and draws one frame per :meth:`Viewer.show`:

- the **reconstruction** as a translucent tube of the catheter's radius, coloured by its local error (the exact
  distance of each point to the true centreline, viridis over ``error_range``) when a truth is given, else by
  |curvature| (the gratings' values interpolated along the tube);
- the **truth** as a thin magenta centreline drawn over everything, so it stays visible at any error, however
  small (the translucent tube around it shows by how much the reconstruction strays);
- the **gratings** as black dots; the **fixture** (tube, groove, sheath) as a faint translucent tube;
- the **interrogator's own shape** (ILLumiSense sensor blocks, :attr:`twin.frames.Frame.vendor`), when the frame
  carries one, as a thin orange centreline, moved onto the reconstruction by the rigid registration the
  reported vendor distance is computed with (:func:`twin.reference_errors.vendor_in_base`), so what is
  drawn is what is reported (its max / mean distance in the overlay). Shown by default; the page's scene
  controls (node ``twin/vendor``) switch it off and on, and ``ViewerConfig.show_vendor`` sets how it starts;
- a **scale bar** (black, a round length) under the catheter, and an overlay: the figures (max / mean / tip
  error when there is a truth, rate, lost frames, the calibration in use, the stream's state) and a legend with
  the colour bar. A stale stream turns the catheter opaque grey.

Placement: a Shape lives in the fibre's base frame; ``base_pose`` puts it in the world, else the truth's base
pose, else a Kabsch registration onto the truth (:func:`twin.viewer.geometry.placement`). The errors shown
are those of the shape as placed (said in the overlay).

Units: geometry is computed in metres. meshcat's scene (grid 0.5 units, camera near plane 0.01) suits ~1 m
objects, so everything hangs under a root node scaled by ``ViewerConfig.scale`` (10: a grid cell is 5 cm)
and centred on the catheter, where the orbit controls turn. The camera is framed on the first frame.

The pieces: :mod:`twin.viewer.view` (the :class:`Viewer` class), :mod:`twin.viewer.geometry` (numpy only),
:mod:`twin.viewer.commands` (meshcat's command format), :mod:`twin.viewer.client` (the zmq client),
:mod:`twin.viewer.server`, :mod:`twin.viewer.sink` (the live loop's sink). Not thread-safe: use from one thread.
"""

from twin.viewer.client import ViewerError
from twin.viewer.geometry import placement, tube_mesh
from twin.viewer.sink import ViewerSink
from twin.viewer.view import CAMERA_FOV_DEG, Viewer, ViewerConfig, keep_open

__all__ = ["CAMERA_FOV_DEG", "Viewer", "ViewerConfig", "ViewerError", "ViewerSink", "keep_open", "placement",
           "tube_mesh"]
