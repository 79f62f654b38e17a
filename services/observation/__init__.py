"""Observation pipeline shared by actors, augmenter and policies: segmented point clouds -> voxel
orthographic projection or rendered depth image -> the policy's uint8 image; for the surgical task,
occupancy voxels -> the per-object DSA image (``dsa``, noise in ``dsa_noise``)."""
