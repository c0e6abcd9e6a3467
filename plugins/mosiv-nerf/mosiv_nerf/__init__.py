"""CoupNeRF* baseline for MOSIV: a voxel radiance field fitted at frame 0, particles sampled from
its density, and volume rendering of simulated particles splatted back onto a grid."""
