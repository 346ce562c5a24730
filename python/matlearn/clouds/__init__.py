"""Point clouds and partial views (method.md section 7): a virtual depth scanner, probabilistic
cloud-surface correspondences (observation residual and Jacobian in C++), a physics-based
tracker, the conversion of cloud recordings to marker recordings, and real-scan ingestion.

Public API:

* :func:`scan_recording`, :class:`ScanSettings`, :class:`Camera`, :func:`default_cameras`,
  :func:`write_cloud_folder` -- virtual scans of simulated motion;
* :func:`correspond`, :class:`CloudObservation`, :func:`surface_samples` -- Gaussian
  correspondences p_kn and the observation residual r_k = sum_n p_kn (c_n - s_k) / sigma^2 with
  its Jacobian; :func:`match_surface` -- point-to-surface matches;
* :func:`track`, :class:`TrackOptions`, :class:`TrackResult` -- tracking the model mesh through
  a cloud sequence; :func:`tracked_markers` -- a cloud recording as a marker recording;
  :func:`refresh_markers` -- the same re-estimated at a new (space-time) trajectory;
* :func:`as_marker_recordings` -- the learning loop's hook: cloud recordings -> tracked markers;
  :func:`markers_scene` -- a whole scene converted (what `matlearn track` writes);
* :func:`make_scene_from_scans` -- a scene from a surface mesh, folders of scans and a clamp box;
* :func:`track_scene`, :func:`cloud_lambda` -- what `matlearn learn` does with cloud recordings:
  track them (cached) and choose the observation weight from the scan noise and the motion.
"""
from .correspondence import CloudObservation, Correspondence, SurfaceMatch, correspond, match_surface, surface_samples
from .ingest import as_marker_recordings, make_scene_from_scans, markers_scene
from .prepare import cloud_lambda, track_scene
from .scanner import Camera, ScanSettings, default_cameras, scan_recording, scan_sequence, write_cloud_folder
from .tracking import TrackOptions, TrackResult, refresh_markers, track, tracked_markers

__all__ = [
    "Camera", "CloudObservation", "Correspondence", "ScanSettings", "SurfaceMatch", "TrackOptions",
    "TrackResult", "as_marker_recordings", "correspond", "default_cameras", "match_surface", "scan_recording",
    "cloud_lambda", "make_scene_from_scans", "markers_scene", "track_scene", "refresh_markers", "scan_sequence", "surface_samples", "track", "tracked_markers", "write_cloud_folder",
]
