"""Surgical Grasp Any (the paper's second domain, after GASv2 on SurRoL), built on pybullet primitives.

Modules: ``settings`` (scale, workspace, action scales, controller, rewards, camera, randomisation),
``instrument`` (the PSM-like tool and its drive), ``objects`` (needle, block, rod), ``scene`` (tray,
placement, constraints), ``camera`` (oblique depth + segmentation, back-projection, image noise),
``control`` (the latched P-controller on the DSA grid's voxel centroids, FSM rewards), ``oracle``
(the scripted discrete policy) and ``env`` (the env and the registry's task class).
"""
