"""The renderer: the GL context, scenes, the frame packer, shaders, framebuffers, draws and reads.
Imports assets and util only."""
