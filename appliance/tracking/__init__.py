"""Where the box phantom is, as the webcam on the image intensifier sees it.

- `tracker.Tracker(phantom, webcam, method, smoothing).track(image, t) -> Pose`: the phantom's
  pose (T_webcam_from_phantom, mm) from one image; `sources.tracker_for(config)` builds it
  from the appliance profile's `tracking` section.
- `sources.open_camera(config)`: the camera the appliance profile names (drivers.camera:
  V4L2Camera, FileCamera, or the SyntheticCamera from `scene.synthetic_camera`).
- `composite.CompositeCalibration`: where each marker sits relative to the root marker.
- `webcam_calibration`: intrinsics from a ChArUco board.
- `trajectory`: scripted phantom paths (configs/trajectories/*.jsonl).
- `commands`: `fluorosim track`, `calibrate webcam|phantom`, `print-markers`, `bench tracking`.
"""
