//! The offscreen targets a view renders into (colour, its multisampled samples, ToF range,
//! depth) and their readback into a [`Frame`].

use super::gpu::{COLOR_FORMAT, DEPTH_FORMAT, Frame, GREY_FORMAT, RANGE_FORMAT, RenderError};

/// The offscreen targets of one (size, shading, pixel samples).
pub(super) struct Targets {
    pub(super) width: u32,
    pub(super) height: u32,
    /// Bytes per pixel of the colour target.
    pub(super) channels: u32,
    /// Row pitch of the colour plane in the readback buffer.
    pub(super) color_bpr: u32,
    /// Row pitch of the range plane in the readback buffer.
    pub(super) range_bpr: u32,
    pub(super) range_offset: u64,
    pub(super) color: wgpu::Texture,
    pub(super) color_view: wgpu::TextureView,
    /// Passive cameras: the multisampled colour target, resolved into `color`.
    pub(super) samples_view: Option<wgpu::TextureView>,
    /// Tof only.
    pub(super) range: Option<(wgpu::Texture, wgpu::TextureView)>,
    pub(super) depth_view: wgpu::TextureView,
    pub(super) readback: wgpu::Buffer,
}

/// Copies a mapped readback buffer into a [`Frame`] and unmaps it (also when the copy fails).
pub(super) fn read_back(t: &Targets) -> Result<Frame, RenderError> {
    let frame = copy_frame(t);
    t.readback.unmap();
    frame
}

fn copy_frame(t: &Targets) -> Result<Frame, RenderError> {
    let (w, h) = (t.width as usize, t.height as usize);
    let row_bytes = w * t.channels as usize;
    let mut pixels = Vec::with_capacity(row_bytes * h);
    let mut range_m = Vec::with_capacity(if t.range.is_some() { w * h } else { 0 });
    // The view is dropped at the end of this function, before the caller unmaps.
    let data = t.readback.slice(..).get_mapped_range().map_err(|e| RenderError::Gpu(e.to_string()))?;
    for row in data.chunks_exact(t.color_bpr as usize).take(h) {
        pixels.extend_from_slice(&row[..row_bytes]);
    }
    if t.range.is_some() {
        let planes = &data[t.range_offset as usize..];
        for row in planes.chunks_exact(t.range_bpr as usize).take(h) {
            range_m.extend(
                row[..w * 4]
                    .chunks_exact(4)
                    .map(|px| f32::from_bits(u32::from_le_bytes([px[0], px[1], px[2], px[3]]))),
            );
        }
    }
    Ok(Frame { width: t.width, height: t.height, pixels, range_m })
}

pub(super) fn create_targets(
    device: &wgpu::Device,
    width: u32,
    height: u32,
    tof: bool,
    samples: u32,
) -> Targets {
    let size = wgpu::Extent3d { width, height, depth_or_array_layers: 1 };
    let make = |label: &str, format: wgpu::TextureFormat, usage: wgpu::TextureUsages, sample_count: u32| {
        device.create_texture(&wgpu::TextureDescriptor {
            label: Some(label),
            size,
            mip_level_count: 1,
            sample_count,
            dimension: wgpu::TextureDimension::D2,
            format,
            usage,
            view_formats: &[],
        })
    };
    let copy_target = wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::COPY_SRC;
    let (color_format, channels) = if tof { (COLOR_FORMAT, 4) } else { (GREY_FORMAT, 1) };
    let color = make("color", color_format, copy_target, 1);
    let samples_view = (samples > 1).then(|| {
        make("samples", color_format, wgpu::TextureUsages::RENDER_ATTACHMENT, samples)
            .create_view(&wgpu::TextureViewDescriptor::default())
    });
    let range = tof.then(|| {
        let range = make("range", RANGE_FORMAT, copy_target, 1);
        let view = range.create_view(&wgpu::TextureViewDescriptor::default());
        (range, view)
    });
    let depth = make("depth", DEPTH_FORMAT, wgpu::TextureUsages::RENDER_ATTACHMENT, samples);

    // Rows of a texture-to-buffer copy are padded to 256 bytes; each plane then is a multiple of 256.
    let align = wgpu::COPY_BYTES_PER_ROW_ALIGNMENT;
    let color_bpr = (width * channels).div_ceil(align) * align;
    let range_bpr = (width * 4).div_ceil(align) * align;
    let range_offset = u64::from(color_bpr) * u64::from(height);
    let range_bytes = if tof { u64::from(range_bpr) * u64::from(height) } else { 0 };
    let readback = device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("readback"),
        size: range_offset + range_bytes,
        usage: wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::MAP_READ,
        mapped_at_creation: false,
    });
    Targets {
        width,
        height,
        channels,
        color_bpr,
        range_bpr,
        range_offset,
        color_view: color.create_view(&wgpu::TextureViewDescriptor::default()),
        samples_view,
        depth_view: depth.create_view(&wgpu::TextureViewDescriptor::default()),
        color,
        range,
        readback,
    }
}
