"""Assets: procedural meshes, checked model and image loading, skinned meshes. Imports util only."""
