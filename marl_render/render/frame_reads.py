"""The renderer's reads: every framebuffer's textures into the batch tensors, straight on the host or
through the GL pixel-pack buffer (to the host, or device to device through the CUDA interop), then
channels-first and the supersampling box filter where the bytes need reshaping.

FrameReads is a base class of BatchRenderer: it reads the renderer's scene, layout, supersample,
channels, channels_first, layered, readback, effects, passes and _texture_ids(), and keeps the
buffers it reuses (_staging, _accumulator, _pack, _pack_layout, _unpack_staging, _interop) on it."""
from __future__ import annotations

import time

import torch

from . import readback
from .framebuffers import RenderPass


class FrameReads:
    """The reads of BatchRenderer (a base class of it: see the module's docstring)."""

    def _read_pass(self, render_pass: RenderPass, rgb, depth, segmentation) -> tuple[float, float]:
        """Read one framebuffer's textures into the outputs on the host; returns the seconds of
        the GL reads and of the copies after them (none for plain channels-last colour and k = 1)."""
        self._texture_ids()
        views, k = render_pass.views, self.supersample
        height, width = self.scene.resolution
        # layered: each view is a layer of rows height * k; the layers follow each other in memory.
        layers = len(views) if self.layered else 1
        rows, columns = len(views) * height * k // layers, width * k
        ids = render_pass.texture_ids
        destination = rgb[views.start:views.stop]
        C = self.channels
        read_seconds = copy_seconds = 0.0
        started = time.perf_counter()
        # One channel is laid out alike channels first or last: read straight into it too.
        if self._color_reads_straight() and self.readback != "copy":
            readback.read_texture(ids["color"], columns, rows, C, destination, layers)
            read_seconds += time.perf_counter() - started
        else:
            staging = self._staging_buffer(layers * rows * columns * C)
            readback.read_texture(ids["color"], columns, rows, C, staging, layers)
            read_seconds += time.perf_counter() - started
            started = time.perf_counter()
            self._finish_color(staging.view(len(views), height * k, width * k, C), destination)
            copy_seconds += time.perf_counter() - started
        for name, out in (("depth", depth), ("segmentation", segmentation)):
            if out is None:
                continue
            target = out[views.start:views.stop]
            started = time.perf_counter()
            if k == 1:
                readback.read_texture(ids[name], columns, rows, 4, target, layers)
                read_seconds += time.perf_counter() - started
                continue
            staging = self._staging_buffer(layers * rows * columns * 4)
            readback.read_texture(ids[name], columns, rows, 4, staging, layers)
            read_seconds += time.perf_counter() - started
            started = time.perf_counter()
            self._finish_aux(staging.view(out.dtype).view(len(views), height * k, width * k), target)
            copy_seconds += time.perf_counter() - started
        return read_seconds, copy_seconds

    def _color_reads_straight(self) -> bool:
        """Whether the colour texture's bytes are the output's: k = 1, and channels last or one channel
        (laid out alike channels first or last)."""
        return self.supersample == 1 and (self.channels == 1 or not self.channels_first)

    def _finish_color(self, samples: torch.Tensor, destination: torch.Tensor) -> None:
        """samples [n, kH, kW, C] as read -> destination (n views of the output): channels first, box filter."""
        if self.channels_first:  # write through a channels-last view of the output
            destination = destination.permute(0, 2, 3, 1)
        if self.supersample > 1:
            self._box_filter(samples, destination)
        else:
            destination.copy_(samples)

    def _finish_aux(self, samples: torch.Tensor, target: torch.Tensor) -> None:
        """Depth or segmentation samples [n, kH, kW] -> target [n, H, W]: the sample nearest each pixel's centre."""
        k = self.supersample
        target.copy_(samples[:, k // 2::k, k // 2::k])

    # ------------------------------------------------------------------ reads through the pack buffer
    def _make_pack_buffer(self) -> None:
        """The pack buffer and where each output lies in it: all views' colour, then all views'
        depth, then segmentation, each as a direct read would give it (so that plain colour, depth
        and segmentation are the output's bytes, copied in one piece)."""
        height, width = self.scene.resolution
        samples = height * width * self.supersample ** 2
        offset = 0
        for name, components in (("color", self.channels), ("depth", 4), ("segmentation", 4)):
            if name == "color" or name in self.effects:
                self._pack_layout[name] = (offset, samples * components)
                offset += self.scene.num_views * samples * components
        self._pack = readback.PackBuffer()
        self._pack.reserve(offset)

    def _read_pass_into_pack(self, render_pass: RenderPass) -> float:
        """Read one framebuffer's textures into the pack buffer at their places; returns the seconds."""
        started = time.perf_counter()
        self._texture_ids()
        views, k = render_pass.views, self.supersample
        height, width = self.scene.resolution
        rows, columns = len(views) * height * k, width * k
        for name, texture in render_pass.texture_ids.items():
            offset, per_view = self._pack_layout[name]
            components = self.channels if name == "color" else 4
            self._pack.read_texture(texture, columns, rows, components, offset + views.start * per_view)
        return time.perf_counter() - started

    def _unpack(self, rgb, depth, segmentation) -> None:
        """The pack buffer into the outputs: each output in one copy (to the host, or device to
        device through the interop), through a staging tensor where it needs reshaping after."""
        k, C = self.supersample, self.channels
        height, width = self.scene.resolution
        copies, finish = [], []
        for name, out in (("color", rgb), ("depth", depth), ("segmentation", segmentation)):
            if out is None:
                continue
            offset, per_view = self._pack_layout[name]
            if (self._color_reads_straight() if name == "color" else k == 1):
                copies.append((offset, out))
                continue
            staging = self._unpack_staging.get(name)
            if staging is None or staging.device != out.device:
                staging = self._unpack_staging[name] = torch.empty(self.scene.num_views * per_view, dtype=torch.uint8,
                                                                   device=out.device)
            copies.append((offset, staging))
            finish.append((name, staging, out))
        if self._interop is not None:
            self._interop.copy(self._pack.name, copies)
        else:
            for offset, destination in copies:
                self._pack.download(offset, destination)
        for name, staging, out in finish:  # per pass: the box filter's accumulator holds one pass
            for render_pass in self._passes:
                views = render_pass.views
                _, per_view = self._pack_layout[name]
                part = staging[views.start * per_view:views.stop * per_view]
                if name == "color":
                    self._finish_color(part.view(len(views), height * k, width * k, C), out[views.start:views.stop])
                else:
                    self._finish_aux(part.view(out.dtype).view(len(views), height * k, width * k),
                                     out[views.start:views.stop])

    def _staging_buffer(self, size: int) -> torch.Tensor:
        """Reused bytes for reads that need a copy afterwards (channels-first, supersampling, "copy")."""
        if self._staging is None or self._staging.numel() < size:
            self._staging = torch.empty(size, dtype=torch.uint8)
        return self._staging[:size]

    def _box_filter(self, samples: torch.Tensor, destination: torch.Tensor) -> None:
        """samples [n, kH, kW, C] uint8 -> destination [n, H, W, C], each pixel the rounded
        mean of its k x k samples (through an accumulator made once per renderer)."""
        k, count, C = self.supersample, destination.shape[0], self.channels
        height, width = self.scene.resolution
        if self._accumulator is None or self._accumulator.device != samples.device:
            self._accumulator = torch.empty((self.layout.views_per_pass, height, width, C), dtype=torch.int32,
                                            device=samples.device)
        total = self._accumulator[:count]
        torch.sum(samples.view(count, height, k, width, k, C), dim=(2, 4), dtype=torch.int32, out=total)
        destination.copy_(total.add_((k * k) // 2).div_(k * k, rounding_mode="floor"))
