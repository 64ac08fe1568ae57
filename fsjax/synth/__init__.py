"""Ground-truth scene and data generators, and the standard input pool.

The pool (:func:`standard_input`) gives every sort a small deterministic
instance; the contract tests, the docs and the evolutionary search feed ops
from it. A family that introduces a sort registers its builder with
:func:`register_pool`.
"""

from ._cross import cad_scan_pair as cad_scan_pair
from ._cross import partial_scan as partial_scan
from ._defects import DEFECT_KINDS as DEFECT_KINDS
from ._defects import Defect as Defect
from ._defects import surface_defects as surface_defects
from ._inspection import bar_code as bar_code
from ._inspection import blurred_disc as blurred_disc
from ._inspection import edge_sweep as edge_sweep
from ._inspection import shaft as shaft
from ._inspection import step_edge as step_edge
from ._inspection import tilted_edge as tilted_edge
from ._lidar import LIDAR_OBJECTS as LIDAR_OBJECTS
from ._lidar import lidar_scene as lidar_scene
from ._match3d import MATCH3D_CELL_TOL as MATCH3D_CELL_TOL
from ._match3d import MATCH3D_METHODS as MATCH3D_METHODS
from ._match3d import MATCH3D_NOT_YET as MATCH3D_NOT_YET
from ._match3d import MATCH3D_STRUCTURES as MATCH3D_STRUCTURES
from ._match3d import match3d_object as match3d_object
from ._match3d import match3d_scene as match3d_scene
from ._match3d import rotation_zyx as rotation_zyx
from ._match3d import run_grid_cell as run_grid_cell
from ._match3d_depth import MATCH3D_DEPTH_CELL_TOL as MATCH3D_DEPTH_CELL_TOL
from ._match3d_depth import MATCH3D_DEPTH_METHODS as MATCH3D_DEPTH_METHODS
from ._match3d_depth import MATCH3D_DEPTH_NOT_APPLICABLE as MATCH3D_DEPTH_NOT_APPLICABLE
from ._match3d_depth import MATCH3D_DEPTH_ONLY_METHODS as MATCH3D_DEPTH_ONLY_METHODS
from ._match3d_depth import MATCH3D_DEPTH_SCALE_TOL as MATCH3D_DEPTH_SCALE_TOL
from ._match3d_depth import match3d_depth_scene as match3d_depth_scene
from ._match3d_depth import run_depth_cell as run_depth_cell
from ._match3d_desc import MATCH3D_DESC_METHODS as MATCH3D_DESC_METHODS
from ._match3d_desc import MATCH3D_DESC_MIN as MATCH3D_DESC_MIN
from ._match3d_desc import MATCH3D_DESC_NOT_YET as MATCH3D_DESC_NOT_YET
from ._match3d_desc import MATCH3D_DESC_STRUCTURES as MATCH3D_DESC_STRUCTURES
from ._match3d_desc import harris3d_repeatability as harris3d_repeatability
from ._match3d_desc import run_descriptor_cell as run_descriptor_cell
from ._match3d_more import MATCH3D_MORE_CELL_TOL as MATCH3D_MORE_CELL_TOL
from ._match3d_more import MATCH3D_MORE_METHODS as MATCH3D_MORE_METHODS
from ._match3d_more import MATCH3D_MORE_NOT_YET as MATCH3D_MORE_NOT_YET
from ._match3d_more import run_more_cell as run_more_cell
from ._match3d_pyr import MATCH3D_PYR_CELL_TOL as MATCH3D_PYR_CELL_TOL
from ._match3d_pyr import MATCH3D_PYR_METHODS as MATCH3D_PYR_METHODS
from ._match3d_shape import MATCH3D_SHAPE_CELL_TOL as MATCH3D_SHAPE_CELL_TOL
from ._match3d_shape import MATCH3D_SHAPE_METHODS as MATCH3D_SHAPE_METHODS
from ._match3d_shape import MATCH3D_SHAPE_NOT_YET as MATCH3D_SHAPE_NOT_YET
from ._match3d_shape import run_shape_cell as run_shape_cell
from ._match3d_shape import turned_shell as turned_shell
from ._multiview import bundle_scene as bundle_scene
from ._particles import particle_scene as particle_scene
from ._phantom import CT_MATERIALS as CT_MATERIALS
from ._phantom import ct_phantom as ct_phantom
from ._phantom import ct_sinogram as ct_sinogram
from ._photometric import angular_error_deg as angular_error_deg
from ._photometric import contaminate_highlights as contaminate_highlights
from ._photometric import highlight_breakdown as highlight_breakdown
from ._photometric import overhead_view as overhead_view
from ._photometric import render_light_stack as render_light_stack
from ._photometric import still_life_scene as still_life_scene
from ._pool import icosphere as icosphere
from ._pool import register_pool as register_pool
from ._pool import standard_input as standard_input
from ._pool import standard_scene as standard_scene
from ._sdf import SDF_KINDS as SDF_KINDS
from ._sdf import sdf_volume as sdf_volume
from ._structured_light import capture_geometry as capture_geometry
from ._structured_light import capture_patterns as capture_patterns
from ._structured_light import decode_depth as decode_depth
from ._structured_light import standard_rig as standard_rig
from ._structured_light import still_life_mm as still_life_mm
from ._video import orbit_video as orbit_video
from ._workpiece import PART_KINDS as PART_KINDS
from ._workpiece import alignment_scene as alignment_scene
from ._workpiece import render_part as render_part
from ._workpiece import workpiece_template as workpiece_template
