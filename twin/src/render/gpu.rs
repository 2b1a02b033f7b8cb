//! The GPU side of the sensor renderer: a headless wgpu device, pipelines drawing textured, lit
//! triangle meshes into an RGBA8 color target and an R32Uint target holding the optical-axis distance
//! in metres (an f32 bit-cast: GL can neither copy depth textures nor render to R32Float, so this
//! works on every backend), and the readback of both.
//!
//! Two programs share the geometry: `fs_grey` (passive cameras lit by the sun: the luminance alone,
//! into one R8 target, which is all a greyscale camera reads back) and `fs_tof` (a Time-of-Flight
//! camera lit by its own emitter: amplitude falls with the square of the range and the cosine of
//! incidence, which it writes with that cosine for the sensor model to use, plus the range target).
//!
//! The WGSL programs are in `scene.wgsl` and `shadow.wgsl` beside this file.
//!
//! Adapter choice: the GPU when there is one, Mesa's software Vulkan (lavapipe) otherwise; the
//! environment variable `WGPU_BACKEND` (`vulkan`, `gl`) forces a backend.

use std::borrow::Cow;
use std::mem::size_of;
use std::sync::mpsc;

use bytemuck::{Pod, Zeroable};
use wgpu::util::DeviceExt;

use super::targets::{Targets, create_targets, read_back};

/// Why the renderer could not start or draw.
#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    /// No adapter: no GPU driver and no software Vulkan.
    #[error(
        "no graphics adapter found ({0}): install Mesa's software Vulkan driver (Debian/Ubuntu packages \
         libvulkan1 and mesa-vulkan-drivers; scripts/setup.sh does it) or a GPU driver"
    )]
    NoAdapter(String),
    /// The device or a pipeline could not be created, or a frame could not be read back.
    #[error("renderer: {0}")]
    Gpu(String),
}

type BoxErr = RenderError;

pub(super) const COLOR_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8Unorm;
pub(super) const GREY_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::R8Unorm;
pub(super) const RANGE_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::R32Uint;
pub(super) const DEPTH_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Depth32Float;
const SHADOW_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Depth32Float;
/// Samples a passive camera's pixel takes of the scene by default, averaged (multisampling): the
/// surfaces that cover a pixel are weighed by the share of its area they cover, as a sensor's pixel
/// integrates the light over its area (each surface is still shaded once a pixel, at its centre;
/// textures are mip-mapped, filtered over the pixel's footprint). With one sample at its centre, a
/// surface narrower than a pixel (the lit side of a canister 25 m away, 2 px wide) is all there in
/// one camera of a pair and missing from the other, which no real pair sees and which stereo
/// cannot match. ToF cameras keep one sample: a range averaged across a depth edge is no surface's.
pub const DEFAULT_PIXEL_SAMPLES: u32 = 4;

/// The sample counts a passive camera's pixel may take (those every adapter supports).
pub const PIXEL_SAMPLES: [u32; 2] = [1, 4];
/// Stride between per-object uniforms; 256 = the default `min_uniform_buffer_offset_alignment`.
const OBJECT_STRIDE: u64 = 256;
const MAX_OBJECTS: u64 = 4096;
/// Most views rendered in one submission.
pub const MAX_VIEWS: usize = 8;

/// The scene programs: passive cameras (one per kind of surface, sky) and Time-of-Flight.
const SHADER: &str = include_str!("scene.wgsl");

/// The depth-only program that draws shadow casters into the shadow map, seen from the sun.
const SHADOW_SHADER: &str = include_str!("shadow.wgsl");

/// Which fragment program a frame uses.
#[derive(Copy, Clone, Debug, PartialEq, Eq)]
pub enum Shading {
    /// Sunlit scene for passive cameras: one luminance byte per pixel, no range.
    Sun,
    /// Active illumination from the camera (Time-of-Flight): color.r = amplitude / 4, color.g = cos i.
    Tof,
}

/// Mesh vertex.
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
pub struct Vertex {
    /// Position in the object frame (m).
    pub position: [f32; 3],
    /// Unit normal in the object frame.
    pub normal: [f32; 3],
    /// Texture coordinates.
    pub uv: [f32; 2],
}

const VERTEX_ATTRS: [wgpu::VertexAttribute; 3] =
    wgpu::vertex_attr_array![0 => Float32x3, 1 => Float32x3, 2 => Float32x2];

/// Per-frame uniforms (group 0). Matrices are column-major.
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
pub struct Globals {
    /// Projection * view.
    pub view_proj: [[f32; 4]; 4],
    /// Camera position (w unused).
    pub cam_pos: [f32; 4],
    /// Unit optical axis (w unused).
    pub cam_fwd: [f32; 4],
    /// Direction towards the sun in xyz, sky ambient (on a level surface) in w.
    pub light_dir: [f32; 4],
    /// World to shadow map: x, y in [-1, 1], depth in [0, 1].
    pub light_view_proj: [[f32; 4]; 4],
    /// x: 1 when the frame has a shadow pass, y: depth bias of the shadow test (z, w unused).
    pub shadow: [f32; 4],
}

/// Object kinds, carried in the tint's alpha (see the shader).
pub mod kind {
    /// The sky dome: emissive, its luminance by direction.
    pub const SKY: f32 = -1.0;
    /// A plain textured object.
    pub const PLAIN: f32 = 1.0;
    /// The terrain: its texture warped by a smooth field (never repeats in view).
    pub const TERRAIN: f32 = 2.0;
    /// A rock: the terrain texture projected on its faces at a small scale.
    pub const ROCK: f32 = 3.0;
}

/// The sun's view of a batch: the shadow casters drawn into the shadow map.
pub struct ShadowPass<'a> {
    /// Uniforms of the pass (`light_view_proj` is what counts).
    pub globals: Globals,
    /// The casters.
    pub draws: Vec<Draw<'a>>,
}

/// Per-draw uniforms (group 2, dynamic offset).
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
pub struct ObjectUniform {
    /// Object-to-world transform.
    pub model: [[f32; 4]; 4],
    /// Multiplies the albedo.
    pub tint: [f32; 4],
}

/// Vertex and index buffers of one mesh.
///
/// Meshes made together by [`Renderer::create_meshes`] share their buffers, so that drawing one
/// after another rebinds nothing (a software driver pays for every state change).
pub struct Mesh {
    vertices: wgpu::Buffer,
    indices: wgpu::Buffer,
    first_index: u32,
    index_count: u32,
}

/// One draw: a mesh, its texture bind group (group 1) and its transform.
#[derive(Clone, Copy)]
pub struct Draw<'a> {
    /// Geometry.
    pub mesh: &'a Mesh,
    /// Bind group made by [`Renderer::create_texture`].
    pub texture: &'a wgpu::BindGroup,
    /// Transform and tint.
    pub object: ObjectUniform,
}

/// One view of a batch: what to draw, from where, into what size.
pub struct View<'a> {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Fragment program and outputs.
    pub shading: Shading,
    /// Samples each pixel takes of the scene, averaged: one of [`PIXEL_SAMPLES`] (ToF shading
    /// takes one whatever this says).
    pub pixel_samples: u32,
    /// Camera and light.
    pub globals: Globals,
    /// What to draw.
    pub draws: Vec<Draw<'a>>,
}

/// One rendered frame, rows tightly packed, row 0 at the top.
pub struct Frame {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// One byte per pixel for [`Shading::Sun`] (luminance), four for [`Shading::Tof`] (RGBA8:
    /// r = amplitude / 4, g = cosine of incidence).
    pub pixels: Vec<u8>,
    /// Distance along the optical axis in metres; 0.0 where nothing was hit. Read back for ToF
    /// shading only (empty for Sun-shaded camera frames).
    pub range_m: Vec<f32>,
}

/// Owns the device, the pipeline and the offscreen targets.
pub struct Renderer {
    device: wgpu::Device,
    queue: wgpu::Queue,
    /// Adapter that was picked (log it: name, backend, driver).
    pub adapter_info: wgpu::AdapterInfo,
    /// Passive cameras: one program per kind of surface (plain, terrain, rock, sky), for each of
    /// [`PIXEL_SAMPLES`].
    grey_pipelines: [[wgpu::RenderPipeline; 4]; 2],
    tof_pipeline: wgpu::RenderPipeline,
    shadow_pipeline: wgpu::RenderPipeline,
    shadow_bgl: wgpu::BindGroupLayout,
    shadow_sampler: wgpu::Sampler,
    /// The shadow map (side, view, group-3 bind group).
    shadow: (u32, wgpu::TextureView, wgpu::BindGroup),
    globals_buf: wgpu::Buffer,
    globals_bg: wgpu::BindGroup,
    objects_buf: wgpu::Buffer,
    objects_bg: wgpu::BindGroup,
    texture_bgl: wgpu::BindGroupLayout,
    sampler: wgpu::Sampler,
    /// Per (width, height, ToF shading, pixel samples, index among the batch's views of that kind).
    targets: std::collections::BTreeMap<(u32, u32, bool, u32, usize), Targets>,
}

impl Renderer {
    /// Opens a device without a window. `WGPU_BACKEND=vulkan|gl` overrides the backend choice.
    pub fn new() -> Result<Self, BoxErr> {
        // Vulkan first, GL only when Vulkan has no adapter: probing GL where EGL cannot load a
        // driver logs errors although Vulkan (lavapipe or a GPU) serves.
        let request = |backends: wgpu::Backends| {
            let mut instance_desc = wgpu::InstanceDescriptor::new_without_display_handle();
            instance_desc.backends = backends;
            instance_desc.flags = wgpu::InstanceFlags::from_build_config().with_env();
            let instance = wgpu::Instance::new(instance_desc);
            pollster::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions {
                power_preference: wgpu::PowerPreference::from_env().unwrap_or_default(),
                force_fallback_adapter: false,
                compatible_surface: None,
                apply_limit_buckets: false,
            }))
        };
        let adapter = match wgpu::Backends::from_env() {
            Some(forced) => request(forced),
            None => request(wgpu::Backends::VULKAN).or_else(|_| request(wgpu::Backends::GL)),
        }
        .map_err(|e| RenderError::NoAdapter(e.to_string()))?;
        let adapter_info = adapter.get_info();

        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("offscreen"),
            required_features: wgpu::Features::empty(),
            required_limits: adapter.limits(),
            experimental_features: wgpu::ExperimentalFeatures::disabled(),
            memory_hints: wgpu::MemoryHints::Performance,
            trace: wgpu::Trace::Off,
        }))
        .map_err(|e| RenderError::Gpu(e.to_string()))?;

        // Turn shader/pipeline validation errors into a Result instead of the default panic.
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);

        let shader = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("scene.wgsl"),
            source: wgpu::ShaderSource::Wgsl(Cow::Borrowed(SHADER)),
        });

        let globals_bgl = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("globals"),
            entries: &[uniform_entry(size_of::<Globals>(), true)],
        });
        let texture_bgl = texture_layout(
            &device,
            "albedo",
            wgpu::TextureSampleType::Float { filterable: true },
            wgpu::SamplerBindingType::Filtering,
        );
        let object_bgl = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("object"),
            entries: &[uniform_entry(size_of::<ObjectUniform>(), true)],
        });

        let shadow_bgl = texture_layout(
            &device,
            "shadow map",
            wgpu::TextureSampleType::Depth,
            wgpu::SamplerBindingType::Comparison,
        );
        let layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("scene"),
            bind_group_layouts: &[
                Some(&globals_bgl),
                Some(&texture_bgl),
                Some(&object_bgl),
                Some(&shadow_bgl),
            ],
            immediate_size: 0,
        });

        let make_pipeline = |vs: &str, fs: &str, targets: &[Option<wgpu::ColorTargetState>], samples: u32| {
            device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
                label: Some("scene"),
                layout: Some(&layout),
                vertex: wgpu::VertexState {
                    module: &shader,
                    entry_point: Some(vs),
                    compilation_options: wgpu::PipelineCompilationOptions::default(),
                    buffers: &[Some(wgpu::VertexBufferLayout {
                        array_stride: size_of::<Vertex>() as u64,
                        step_mode: wgpu::VertexStepMode::Vertex,
                        attributes: &VERTEX_ATTRS,
                    })],
                },
                primitive: wgpu::PrimitiveState {
                    topology: wgpu::PrimitiveTopology::TriangleList,
                    strip_index_format: None,
                    front_face: wgpu::FrontFace::Ccw,
                    cull_mode: Some(wgpu::Face::Back),
                    unclipped_depth: false,
                    polygon_mode: wgpu::PolygonMode::Fill,
                    conservative: false,
                },
                depth_stencil: Some(wgpu::DepthStencilState {
                    format: DEPTH_FORMAT,
                    depth_write_enabled: Some(true),
                    depth_compare: Some(wgpu::CompareFunction::Less),
                    stencil: wgpu::StencilState::default(),
                    bias: wgpu::DepthBiasState::default(),
                }),
                multisample: wgpu::MultisampleState { count: samples, ..Default::default() },
                fragment: Some(wgpu::FragmentState {
                    module: &shader,
                    entry_point: Some(fs),
                    compilation_options: wgpu::PipelineCompilationOptions::default(),
                    targets,
                }),
                multiview_mask: None,
                cache: None,
            })
        };
        let target =
            |format| Some(wgpu::ColorTargetState { format, blend: None, write_mask: wgpu::ColorWrites::ALL });
        let grey = [target(GREY_FORMAT)];
        let grey_pipelines = PIXEL_SAMPLES.map(|samples| {
            [
                make_pipeline("vs_grey", "fs_grey", &grey, samples),
                make_pipeline("vs_terrain", "fs_terrain", &grey, samples),
                make_pipeline("vs_rock", "fs_grey", &grey, samples),
                make_pipeline("vs_sky", "fs_sky", &grey, samples),
            ]
        });
        // Same blend/write_mask on both targets: no INDEPENDENT_BLEND needed on GL.
        let tof_pipeline =
            make_pipeline("vs_main", "fs_tof", &[target(COLOR_FORMAT), target(RANGE_FORMAT)], 1);

        // The shadow casters seen from the sun: depth only, both faces (thin parts), biased by
        // slope against self-shadowing.
        let shadow_shader = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("shadow.wgsl"),
            source: wgpu::ShaderSource::Wgsl(Cow::Borrowed(SHADOW_SHADER)),
        });
        let shadow_layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("shadow"),
            bind_group_layouts: &[Some(&globals_bgl), Some(&object_bgl)],
            immediate_size: 0,
        });
        let shadow_pipeline = device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
            label: Some("shadow"),
            layout: Some(&shadow_layout),
            vertex: wgpu::VertexState {
                module: &shadow_shader,
                entry_point: Some("vs_shadow"),
                compilation_options: wgpu::PipelineCompilationOptions::default(),
                buffers: &[Some(wgpu::VertexBufferLayout {
                    array_stride: size_of::<Vertex>() as u64,
                    step_mode: wgpu::VertexStepMode::Vertex,
                    attributes: &VERTEX_ATTRS[..1],
                })],
            },
            primitive: wgpu::PrimitiveState { cull_mode: None, ..Default::default() },
            depth_stencil: Some(wgpu::DepthStencilState {
                format: SHADOW_FORMAT,
                depth_write_enabled: Some(true),
                depth_compare: Some(wgpu::CompareFunction::Less),
                stencil: wgpu::StencilState::default(),
                bias: wgpu::DepthBiasState { constant: 2, slope_scale: 2.0, clamp: 0.0 },
            }),
            multisample: wgpu::MultisampleState::default(),
            fragment: None,
            multiview_mask: None,
            cache: None,
        });

        if let Some(err) = pollster::block_on(scope.pop()) {
            return Err(RenderError::Gpu(format!("pipeline creation failed: {err}")));
        }

        // One slot per view and one for the shadow pass.
        let (globals_buf, globals_bg) =
            dynamic_uniform(&device, &globals_bgl, "globals", MAX_VIEWS as u64 + 1, size_of::<Globals>());
        let (objects_buf, objects_bg) =
            dynamic_uniform(&device, &object_bgl, "objects", MAX_OBJECTS, size_of::<ObjectUniform>());
        let sampler = device.create_sampler(&wgpu::SamplerDescriptor {
            label: Some("albedo"),
            address_mode_u: wgpu::AddressMode::Repeat,
            address_mode_v: wgpu::AddressMode::Repeat,
            mag_filter: wgpu::FilterMode::Linear,
            min_filter: wgpu::FilterMode::Linear,
            mipmap_filter: wgpu::MipmapFilterMode::Nearest,
            ..Default::default()
        });

        let shadow_sampler = device.create_sampler(&wgpu::SamplerDescriptor {
            label: Some("shadow"),
            address_mode_u: wgpu::AddressMode::ClampToEdge,
            address_mode_v: wgpu::AddressMode::ClampToEdge,
            // One texel per lookup: a 2 x 2 filter costs a software rasterizer four.
            mag_filter: wgpu::FilterMode::Nearest,
            min_filter: wgpu::FilterMode::Nearest,
            compare: Some(wgpu::CompareFunction::LessEqual),
            ..Default::default()
        });
        let shadow = make_shadow_map(&device, &shadow_bgl, &shadow_sampler, DEFAULT_SHADOW_MAP_PX);
        let targets = Default::default();
        Ok(Self {
            device,
            queue,
            adapter_info,
            grey_pipelines,
            tof_pipeline,
            shadow_pipeline,
            shadow_bgl,
            shadow_sampler,
            shadow,
            globals_buf,
            globals_bg,
            objects_buf,
            objects_bg,
            texture_bgl,
            sampler,
            targets,
        })
    }

    /// Sets the side of the (square) shadow map, pixels.
    pub fn set_shadow_map_px(&mut self, px: u32) {
        let px = px.clamp(16, 8192);
        if px != self.shadow.0 {
            self.shadow = make_shadow_map(&self.device, &self.shadow_bgl, &self.shadow_sampler, px);
        }
    }

    /// Uploads an RGBA8 image (terrain albedo, marker) and returns its group-1 bind group.
    pub fn create_texture(&self, width: u32, height: u32, rgba: &[u8]) -> wgpu::BindGroup {
        // A full mip chain (box-filtered here): minified texture reads stay in cache, which a
        // software rasterizer feels most.
        let levels = 32 - width.max(height).leading_zeros();
        let size = wgpu::Extent3d { width, height, depth_or_array_layers: 1 };
        let texture = self.device.create_texture(&wgpu::TextureDescriptor {
            label: Some("albedo"),
            size,
            mip_level_count: levels,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: wgpu::TextureFormat::Rgba8Unorm,
            usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
            view_formats: &[],
        });
        let (mut w, mut h, mut level) = (width, height, rgba.to_vec());
        for mip in 0..levels {
            self.queue.write_texture(
                wgpu::TexelCopyTextureInfo {
                    texture: &texture,
                    mip_level: mip,
                    origin: wgpu::Origin3d::ZERO,
                    aspect: wgpu::TextureAspect::All,
                },
                &level,
                wgpu::TexelCopyBufferLayout {
                    offset: 0,
                    bytes_per_row: Some(4 * w), // no 256 alignment needed for write_texture
                    rows_per_image: Some(h),
                },
                wgpu::Extent3d { width: w, height: h, depth_or_array_layers: 1 },
            );
            let (nw, nh) = ((w / 2).max(1), (h / 2).max(1));
            let mut next = Vec::with_capacity((nw * nh * 4) as usize);
            for y in 0..nh {
                for x in 0..nw {
                    for c in 0..4 {
                        let at = |xx: u32, yy: u32| {
                            level[((yy.min(h - 1) * w + xx.min(w - 1)) * 4 + c) as usize] as u32
                        };
                        let sum = at(2 * x, 2 * y)
                            + at(2 * x + 1, 2 * y)
                            + at(2 * x, 2 * y + 1)
                            + at(2 * x + 1, 2 * y + 1);
                        next.push(((sum + 2) / 4) as u8);
                    }
                }
            }
            (w, h, level) = (nw, nh, next);
        }
        let view = texture.create_view(&wgpu::TextureViewDescriptor::default());
        self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("albedo"),
            layout: &self.texture_bgl,
            entries: &[
                wgpu::BindGroupEntry { binding: 0, resource: wgpu::BindingResource::TextureView(&view) },
                wgpu::BindGroupEntry { binding: 1, resource: wgpu::BindingResource::Sampler(&self.sampler) },
            ],
        })
    }

    /// Uploads triangle meshes into one vertex and one index buffer (none may be empty:
    /// `set_vertex_buffer` panics on empty slices).
    pub fn create_meshes(&self, meshes: &[(&[Vertex], &[u32])]) -> Vec<Mesh> {
        // Each mesh's indices are offset by the vertices before it: draws need no base vertex,
        // which GLES 3.0 lacks.
        let vertices: Vec<Vertex> = meshes.iter().flat_map(|m| m.0.iter().copied()).collect();
        let mut indices: Vec<u32> = Vec::with_capacity(meshes.iter().map(|m| m.1.len()).sum());
        let mut base = 0u32;
        for (v, i) in meshes {
            indices.extend(i.iter().map(|k| k + base));
            base += v.len() as u32;
        }
        let vertices_buf = self.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("vertices"),
            contents: bytemuck::cast_slice(&vertices),
            usage: wgpu::BufferUsages::VERTEX,
        });
        let indices_buf = self.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("indices"),
            contents: bytemuck::cast_slice(&indices),
            usage: wgpu::BufferUsages::INDEX,
        });
        let mut first_index = 0u32;
        meshes
            .iter()
            .map(|(_, i)| {
                let mesh = Mesh {
                    vertices: vertices_buf.clone(),
                    indices: indices_buf.clone(),
                    first_index,
                    index_count: i.len() as u32,
                };
                first_index += i.len() as u32;
                mesh
            })
            .collect()
    }

    /// Renders several views in one submission and reads them all back: luminance for
    /// [`Shading::Sun`], colour and range for [`Shading::Tof`] (a stereo pair: the rasterizer shades
    /// one view while the next one's geometry is processed, and there is one wait instead of two).
    ///
    /// With a `shadow` pass, its casters are first drawn into the shadow map from the sun; the
    /// views' fragments then test against it (their globals say whether to).
    pub fn render_views(
        &mut self,
        views: &[View<'_>],
        shadow: Option<&ShadowPass<'_>>,
    ) -> Result<Vec<Frame>, BoxErr> {
        if views.len() > MAX_VIEWS {
            return Err(RenderError::Gpu(format!("too many views: {} > {MAX_VIEWS}", views.len())));
        }
        let total: usize =
            views.iter().map(|v| v.draws.len()).sum::<usize>() + shadow.map(|s| s.draws.len()).unwrap_or(0);
        if total as u64 > MAX_OBJECTS {
            return Err(RenderError::Gpu(format!("too many draws: {total} > {MAX_OBJECTS}")));
        }
        // The targets of each view: views of the same size and kind get their own.
        let mut keys = Vec::with_capacity(views.len());
        for v in views {
            let tof = matches!(v.shading, Shading::Tof);
            let samples = if tof { 1 } else { v.pixel_samples };
            if !PIXEL_SAMPLES.contains(&samples) {
                return Err(RenderError::Gpu(format!(
                    "pixel samples must be one of {PIXEL_SAMPLES:?}, got {samples}"
                )));
            }
            let n = keys
                .iter()
                .filter(|k: &&(u32, u32, bool, u32, usize)| {
                    (k.0, k.1, k.2, k.3) == (v.width, v.height, tof, samples)
                })
                .count();
            let key = (v.width, v.height, tof, samples, n);
            self.targets
                .entry(key)
                .or_insert_with(|| create_targets(&self.device, v.width, v.height, tof, samples));
            keys.push(key);
        }
        // One upload for all per-view and per-draw uniforms (a write each costs a staging
        // allocation); a draw with the same transform and tint as the one before shares its slot.
        let passes: Vec<(&Globals, &[Draw<'_>])> = views
            .iter()
            .map(|v| (&v.globals, &v.draws[..]))
            .chain(shadow.map(|s| (&s.globals, &s.draws[..])))
            .collect();
        let mut globals = vec![0u8; passes.len() * OBJECT_STRIDE as usize];
        let mut objects: Vec<u8> = Vec::with_capacity(total * OBJECT_STRIDE as usize);
        let mut slots: Vec<Vec<u32>> = Vec::with_capacity(passes.len());
        for (k, (g, draws)) in passes.iter().enumerate() {
            let bytes = bytemuck::bytes_of(*g);
            globals[k * OBJECT_STRIDE as usize..][..bytes.len()].copy_from_slice(bytes);
            let mut view_slots = Vec::with_capacity(draws.len());
            let mut last: Option<&ObjectUniform> = None;
            for d in draws.iter() {
                if last.is_none_or(|l| bytemuck::bytes_of(l) != bytemuck::bytes_of(&d.object)) {
                    let at = objects.len();
                    objects.resize(at + OBJECT_STRIDE as usize, 0);
                    let bytes = bytemuck::bytes_of(&d.object);
                    objects[at..at + bytes.len()].copy_from_slice(bytes);
                }
                view_slots.push((objects.len() as u64 - OBJECT_STRIDE) as u32);
                last = Some(&d.object);
            }
            slots.push(view_slots);
        }
        self.queue.write_buffer(&self.globals_buf, 0, &globals);
        if !objects.is_empty() {
            self.queue.write_buffer(&self.objects_buf, 0, &objects);
        }

        let mut encoder =
            self.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("frame") });
        if let Some(sp) = shadow {
            let k = views.len();
            let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
                label: Some("shadow"),
                color_attachments: &[],
                depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                    view: &self.shadow.1,
                    depth_ops: Some(wgpu::Operations {
                        load: wgpu::LoadOp::Clear(1.0),
                        store: wgpu::StoreOp::Store,
                    }),
                    stencil_ops: None,
                }),
                timestamp_writes: None,
                occlusion_query_set: None,
                multiview_mask: None,
            });
            pass.set_pipeline(&self.shadow_pipeline);
            pass.set_bind_group(0, &self.globals_bg, &[(k as u64 * OBJECT_STRIDE) as u32]);
            let mut binder = Binder::default();
            for (d, &offset) in sp.draws.iter().zip(&slots[k]) {
                binder.draw(&mut pass, &self.objects_bg, (1, None), d, offset);
            }
        }
        for (k, (v, key)) in views.iter().zip(&keys).enumerate() {
            let t = &self.targets[key];
            {
                let attachment = |view| {
                    Some(wgpu::RenderPassColorAttachment {
                        view,
                        depth_slice: None,
                        resolve_target: None,
                        ops: wgpu::Operations {
                            // Black; the integer range target casts each f64 `as u32` -> clears to 0.
                            load: wgpu::LoadOp::Clear(wgpu::Color { r: 0.0, g: 0.0, b: 0.0, a: 1.0 }),
                            store: wgpu::StoreOp::Store,
                        },
                    })
                };
                let mut color_attachments = match &t.samples_view {
                    // The samples are averaged into `color`; they need not be kept.
                    Some(samples) => vec![attachment(samples).map(|a| wgpu::RenderPassColorAttachment {
                        resolve_target: Some(&t.color_view),
                        ops: wgpu::Operations { store: wgpu::StoreOp::Discard, ..a.ops },
                        ..a
                    })],
                    None => vec![attachment(&t.color_view)],
                };
                if let Some((_, view)) = &t.range {
                    color_attachments.push(attachment(view));
                }
                let mut pass = encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
                    label: Some("scene"),
                    color_attachments: &color_attachments,
                    depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                        view: &t.depth_view,
                        depth_ops: Some(wgpu::Operations {
                            load: wgpu::LoadOp::Clear(1.0),
                            store: wgpu::StoreOp::Discard,
                        }),
                        stencil_ops: None,
                    }),
                    timestamp_writes: None,
                    occlusion_query_set: None,
                    multiview_mask: None,
                });
                // ToF: one program; passive cameras: the program of each draw's kind of surface.
                let program = |tint: &[f32; 4]| match tint[3] {
                    a if a < 0.0 => 3,
                    a if a > 2.5 => 2,
                    a if a > 1.5 => 1,
                    _ => 0,
                };
                let mut current = None;
                let samples_at = PIXEL_SAMPLES.iter().position(|&n| n == key.3).unwrap_or(0);
                let grey_pipelines = &self.grey_pipelines[samples_at];
                if key.2 {
                    pass.set_pipeline(&self.tof_pipeline);
                }
                pass.set_bind_group(0, &self.globals_bg, &[(k as u64 * OBJECT_STRIDE) as u32]);
                pass.set_bind_group(3, &self.shadow.2, &[]);
                let mut binder = Binder::default();
                for (d, &offset) in v.draws.iter().zip(&slots[k]) {
                    let p = program(&d.object.tint);
                    if !key.2 && current != Some(p) {
                        pass.set_pipeline(&grey_pipelines[p]);
                        current = Some(p);
                    }
                    binder.draw(&mut pass, &self.objects_bg, (2, Some(1)), d, offset);
                }
            } // pass dropped: encoder usable again

            let extent = wgpu::Extent3d { width: t.width, height: t.height, depth_or_array_layers: 1 };
            let plane = |offset: u64, bytes_per_row: u32| wgpu::TexelCopyBufferInfo {
                buffer: &t.readback,
                layout: wgpu::TexelCopyBufferLayout {
                    offset,
                    bytes_per_row: Some(bytes_per_row),
                    rows_per_image: Some(t.height),
                },
            };
            encoder.copy_texture_to_buffer(t.color.as_image_copy(), plane(0, t.color_bpr), extent);
            if let Some((range, _)) = &t.range {
                encoder.copy_texture_to_buffer(
                    range.as_image_copy(),
                    plane(t.range_offset, t.range_bpr),
                    extent,
                );
            }
        }
        let submission = self.queue.submit([encoder.finish()]);

        let (tx, rx) = mpsc::channel();
        for (n, key) in keys.iter().enumerate() {
            let tx = tx.clone();
            self.targets[key].readback.slice(..).map_async(wgpu::MapMode::Read, move |result| {
                let _ = tx.send((n, result));
            });
        }
        drop(tx);
        self.device
            .poll(wgpu::PollType::Wait { submission_index: Some(submission), timeout: None })
            .map_err(|e| RenderError::Gpu(e.to_string()))?;
        // Every buffer that was mapped is read and unmapped, whatever else failed: the next copy
        // into a buffer left mapped would be an error.
        let mut mapped = vec![false; keys.len()];
        let mut error = None;
        for _ in &keys {
            match rx.recv() {
                Ok((n, Ok(()))) => mapped[n] = true,
                Ok((_, Err(e))) => _ = error.get_or_insert(RenderError::Gpu(e.to_string())),
                Err(e) => {
                    error.get_or_insert(RenderError::Gpu(e.to_string()));
                    break;
                }
            }
        }
        let mut frames = Vec::with_capacity(keys.len());
        for (key, _) in keys.iter().zip(&mapped).filter(|(_, m)| **m) {
            match read_back(&self.targets[key]) {
                Ok(f) => frames.push(f),
                Err(e) => _ = error.get_or_insert(e),
            }
        }
        match error {
            Some(e) => Err(e),
            None => Ok(frames),
        }
    }
}

/// Issues draws, binding only what changes from one draw to the next (a software driver pays for
/// every state change).
#[derive(Default)]
struct Binder<'a> {
    texture: Option<&'a wgpu::BindGroup>,
    slot: Option<u32>,
    buffers: Option<(&'a wgpu::Buffer, &'a wgpu::Buffer)>,
}

impl<'a> Binder<'a> {
    /// Draws `d` with its per-object uniforms at `offset` of `objects`, bound at group
    /// `groups.0`, and its texture at group `groups.1` (none: the program samples no texture).
    fn draw(
        &mut self,
        pass: &mut wgpu::RenderPass<'_>,
        objects: &wgpu::BindGroup,
        groups: (u32, Option<u32>),
        d: &Draw<'a>,
        offset: u32,
    ) {
        if let Some(g) = groups.1
            && self.texture != Some(d.texture)
        {
            pass.set_bind_group(g, d.texture, &[]);
            self.texture = Some(d.texture);
        }
        if self.slot != Some(offset) {
            pass.set_bind_group(groups.0, objects, &[offset]);
            self.slot = Some(offset);
        }
        if self.buffers != Some((&d.mesh.vertices, &d.mesh.indices)) {
            pass.set_vertex_buffer(0, d.mesh.vertices.slice(..));
            pass.set_index_buffer(d.mesh.indices.slice(..), wgpu::IndexFormat::Uint32);
            self.buffers = Some((&d.mesh.vertices, &d.mesh.indices));
        }
        let first = d.mesh.first_index;
        pass.draw_indexed(first..first + d.mesh.index_count, 0, 0..1);
    }
}

/// Side of the shadow map until [`Renderer::set_shadow_map_px`] says otherwise, pixels.
pub const DEFAULT_SHADOW_MAP_PX: u32 = 1024;

/// A square depth texture of `px` pixels for the shadow pass, and its group-3 bind group.
fn make_shadow_map(
    device: &wgpu::Device,
    layout: &wgpu::BindGroupLayout,
    sampler: &wgpu::Sampler,
    px: u32,
) -> (u32, wgpu::TextureView, wgpu::BindGroup) {
    let texture = device.create_texture(&wgpu::TextureDescriptor {
        label: Some("shadow map"),
        size: wgpu::Extent3d { width: px, height: px, depth_or_array_layers: 1 },
        mip_level_count: 1,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D2,
        format: SHADOW_FORMAT,
        usage: wgpu::TextureUsages::RENDER_ATTACHMENT | wgpu::TextureUsages::TEXTURE_BINDING,
        view_formats: &[],
    });
    let view = texture.create_view(&wgpu::TextureViewDescriptor::default());
    let group = device.create_bind_group(&wgpu::BindGroupDescriptor {
        label: Some("shadow map"),
        layout,
        entries: &[
            wgpu::BindGroupEntry { binding: 0, resource: wgpu::BindingResource::TextureView(&view) },
            wgpu::BindGroupEntry { binding: 1, resource: wgpu::BindingResource::Sampler(sampler) },
        ],
    });
    (px, view, group)
}

/// A uniform buffer of `slots` entries `OBJECT_STRIDE` apart and its bind group, which binds one
/// entry of `size` bytes at the dynamic offset given with each draw.
fn dynamic_uniform(
    device: &wgpu::Device,
    layout: &wgpu::BindGroupLayout,
    label: &str,
    slots: u64,
    size: usize,
) -> (wgpu::Buffer, wgpu::BindGroup) {
    let buffer = device.create_buffer(&wgpu::BufferDescriptor {
        label: Some(label),
        size: OBJECT_STRIDE * slots,
        usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    let group = device.create_bind_group(&wgpu::BindGroupDescriptor {
        label: Some(label),
        layout,
        entries: &[wgpu::BindGroupEntry {
            binding: 0,
            resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                buffer: &buffer,
                offset: 0,
                size: wgpu::BufferSize::new(size as u64),
            }),
        }],
    });
    (buffer, group)
}

/// Layout of a fragment-stage texture (binding 0) and its sampler (binding 1).
fn texture_layout(
    device: &wgpu::Device,
    label: &str,
    sample_type: wgpu::TextureSampleType,
    sampler: wgpu::SamplerBindingType,
) -> wgpu::BindGroupLayout {
    device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
        label: Some(label),
        entries: &[
            wgpu::BindGroupLayoutEntry {
                binding: 0,
                visibility: wgpu::ShaderStages::FRAGMENT,
                ty: wgpu::BindingType::Texture {
                    sample_type,
                    view_dimension: wgpu::TextureViewDimension::D2,
                    multisampled: false,
                },
                count: None,
            },
            wgpu::BindGroupLayoutEntry {
                binding: 1,
                visibility: wgpu::ShaderStages::FRAGMENT,
                ty: wgpu::BindingType::Sampler(sampler),
                count: None,
            },
        ],
    })
}

/// Layout entry of a uniform buffer at binding 0, seen by both shader stages.
fn uniform_entry(size: usize, dynamic: bool) -> wgpu::BindGroupLayoutEntry {
    wgpu::BindGroupLayoutEntry {
        binding: 0,
        visibility: wgpu::ShaderStages::VERTEX_FRAGMENT,
        ty: wgpu::BindingType::Buffer {
            ty: wgpu::BufferBindingType::Uniform,
            has_dynamic_offset: dynamic,
            min_binding_size: wgpu::BufferSize::new(size as u64),
        },
        count: None,
    }
}
