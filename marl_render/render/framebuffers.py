"""The renderer's framebuffers: one per column of views (or, layered, per array of layers), each with
its own scene root, camera and render textures (colour, and depth / segmentation as aux targets)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import backend, shaders
from .panda_buffers import clip_distances, int_input


@dataclass
class RenderPass:
    """One framebuffer: a column of up to layout.rows views, its scene root and render textures."""

    views: range
    buffer: object  # Panda3D GraphicsBuffer
    root: object  # NodePath holding this pass's copy of every group node
    color: object  # Texture rendered into (RGBA8)
    aux: dict  # name -> Texture of the depth / segmentation outputs
    texture_ids: dict | None = None  # GL names of the textures, known after the first frame


def make_pass(context: backend.GLContext, layout, views: range, *, effects: frozenset, multisamples: int, gray: bool,
              layered: bool, background, shared_inputs: dict) -> RenderPass:
    """The framebuffer of `views` (a range of the tile layout's views) and its scene root, inactive
    until a frame is drawn; `shared_inputs` are the shader inputs every pass sets on its root."""
    from panda3d.core import (
        Camera,
        ColorBlendAttrib,
        CullFaceAttrib,
        DepthTestAttrib,
        DepthWriteAttrib,
        FrameBufferProperties,
        GraphicsOutput,
        GraphicsPipe,
        NodePath,
        OmniBoundingVolume,
        Texture,
        TransparencyAttrib,
        WindowProperties,
    )

    width, height = layout.tile_width, layout.tile_height * (1 if layered else len(views))
    aux_names = [e for e in ("depth", "segmentation") if e in effects]
    props = FrameBufferProperties()
    props.set_rgba_bits(8, 8, 8, 8)
    props.set_depth_bits(24)
    props.set_aux_rgba(len(aux_names))
    props.set_multisamples(multisamples)
    # One name for all buffers: Panda3D keeps a statistics collector per buffer name
    # for the life of the process (a unique name per renderer leaked about 3 KB each).
    buffer = context.engine.make_output(
        context.pipe, "marl_render", 0, props, WindowProperties.size(width, height),
        GraphicsPipe.BF_refuse_window, context.gsg, context.host)
    if buffer is None:
        samples = f" and {multisamples} MSAA samples (multisamples)" if multisamples else ""
        raise backend.GLUnavailableError(
            f"could not create a {width}x{height} offscreen framebuffer with {len(aux_names)} aux targets"
            f"{samples}; lower resolution / num views{', multisamples' if samples else ''} or max_framebuffer_size")
    granted = buffer.get_fb_properties().get_multisamples()
    if granted < multisamples:  # the GL may hand out fewer samples without failing: refuse, not alias
        context.engine.remove_window(buffer)
        raise backend.GLUnavailableError(
            f"multisamples={multisamples} was asked for but the GL ({context.gsg.get_driver_renderer()}) "
            f"gave {granted}; lower multisamples (or use supersample)")
    # Render into textures that stay in GL; readback.py reads them once all passes are drawn.
    # layered: one array texture layer per view, all attached at once (Panda3D makes its depth
    # buffer a layered texture too); a vertex shader picks the layer (gl_Layer).
    mode = GraphicsOutput.RTM_bind_layered if layered else GraphicsOutput.RTM_bind_or_copy
    color = Texture("color")
    if layered:
        color.setup_2d_texture_array(len(views))
    buffer.add_render_texture(color, mode, GraphicsOutput.RTP_color)
    aux = {}
    for index, name in enumerate(aux_names):
        texture = Texture(name)
        if layered:
            texture.setup_2d_texture_array(len(views))
        plane = GraphicsOutput.RTP_aux_rgba_0 + index
        buffer.add_render_texture(texture, mode, plane)
        # Clear values as RGBA bytes of the little-endian value: depth +inf (0x7f800000), segment 0.
        clear = (0.0, 0.0, 128 / 255, 127 / 255) if name == "depth" else (0.0, 0.0, 0.0, 0.0)
        buffer.set_clear_active(plane, True)
        buffer.set_clear_value(plane, clear)
        aux[name] = texture
    context.drop_render_texture_events()
    background = np.asarray(background[:3], dtype=float)
    if gray:  # the shader's luma of the background
        background = np.full(3, float(np.dot(background, shaders.GRAY_WEIGHTS)))
    buffer.set_clear_color(tuple(background) + (1.0,))
    buffer.set_clear_color_active("appearance" not in effects)  # the sky is copied over every tile instead
    buffer.set_active(False)

    root = NodePath(f"marl_render_pass_{views.start}")
    camera = Camera("tiles")
    camera.set_cull_bounds(OmniBoundingVolume())
    buffer.make_display_region().set_camera(root.attach_new_node(camera))
    # The per-view vertical flip reverses winding: cull the other side.
    root.set_attrib(CullFaceAttrib.make(CullFaceAttrib.M_cull_counter_clockwise))
    root.set_attrib(DepthTestAttrib.make(DepthTestAttrib.M_less))
    root.set_attrib(DepthWriteAttrib.make(DepthWriteAttrib.M_on))
    root.set_transparency(TransparencyAttrib.M_none)
    root.set_attrib(ColorBlendAttrib.make_off())
    if not layered:
        root.set_attrib(clip_distances(2))  # the tiles' top and bottom (shaders/batch.vert)
    for name, value in shared_inputs.items():
        root.set_shader_input(name, value)
    root.set_shader_input("tiles", int_input(len(views)))
    root.set_shader_input("view_offset", int_input(views.start))
    return RenderPass(views, buffer, root, color, aux)
