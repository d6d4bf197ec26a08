"""The volume: the hypothesis TSDF over Open3D's VoxelBlockGrid (III-A, III-C), the per-voxel
vote (eqs. 5-6), marching cubes with hypotheses on the vertices, the archive of blocks that
left the active window, and the rigid move of blocks after a pose correction.

``tsdf`` (the volume) builds on ``grid`` (blocks, window, archive, moves), ``hypotheses`` (the
vote), ``mesh`` (marching cubes), ``window`` (the archive's storage) and ``move`` (block
motion; its numba kernels in ``move_numba``)."""
