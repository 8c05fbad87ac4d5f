"""The monocular odometry pipeline (paper Fig. 2b): map initialisation, triangulation,
keyframe selection, failure handling, wired around the frontend and the backend."""
