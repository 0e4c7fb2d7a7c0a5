"""What a run refines besides the scene: the cameras and the sensor.

    lens             each training camera's intrinsics, learnt through the rays they define
    pose_solve       a Levenberg-Marquardt solve of the training poses against the current scene
    refined_frame    the similarity between the frame the cameras were given in and the scene's
    refined_cameras  the refined cameras written beside a run (cameras_refined.json, a COLMAP text model)
    appearance       per-image exposure and white balance, per-camera vignetting
"""
