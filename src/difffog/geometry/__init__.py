"""Geometry on the host, once per scene: the lattice (voxelization), the lattice's direction
set, triangle meshes of the shapes and ray casting against them."""
