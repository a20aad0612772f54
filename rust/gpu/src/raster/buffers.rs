//! Device buffers: the grow-only pool of named storage buffers, the check against the
//! adapter's binding limits, uploads, uniforms and readbacks, and the buffers a forward leaves
//! for its backward. Apart from the rasterizer's stages, which only name the buffers they need.

use std::collections::HashMap;

use wgpu::util::DeviceExt;

use super::rasterizer::GpuRasterizer;
use crate::device::GpuDevice;
use crate::error::{GpuError, Result};

/// Grow-only named storage buffers, reused across calls.
#[derive(Default)]
pub(super) struct Pool {
    buffers: HashMap<&'static str, wgpu::Buffer>,
}

const STORAGE: wgpu::BufferUsages = wgpu::BufferUsages::STORAGE
    .union(wgpu::BufferUsages::COPY_DST)
    .union(wgpu::BufferUsages::COPY_SRC);

impl Pool {
    /// A buffer of at least `bytes` bytes (and at least 16) under `name`.
    fn get(
        &mut self,
        dev: &wgpu::Device,
        name: &'static str,
        bytes: u64,
        usage: wgpu::BufferUsages,
    ) -> wgpu::Buffer {
        let bytes = bytes.max(16).next_multiple_of(16);
        if let Some(b) = self.buffers.get(name) {
            if b.size() >= bytes {
                return b.clone();
            }
        }
        let b = dev.create_buffer(&wgpu::BufferDescriptor {
            label: Some(name),
            size: bytes.next_power_of_two().max(bytes),
            usage,
            mapped_at_creation: false,
        });
        self.buffers.insert(name, b.clone());
        b
    }
}

/// The device buffers both compositing kernels read.
pub(super) struct ForwardBuffers {
    pub(super) splats: wgpu::Buffer,
    pub(super) ids: wgpu::Buffer,
    pub(super) tile_offsets: wgpu::Buffer,
    pub(super) features: wgpu::Buffer,
    pub(super) pixel_state: wgpu::Buffer,
}

impl ForwardBuffers {
    /// Their bindings (blend.wgsl 1, 3-5 and 7).
    pub(super) fn bindings(&self) -> [(u32, &wgpu::Buffer); 5] {
        [
            (1, &self.splats),
            (3, &self.ids),
            (4, &self.tile_offsets),
            (5, &self.features),
            (7, &self.pixel_state),
        ]
    }
}

fn check_binding(gpu: &GpuDevice, what: &str, bytes: u64) -> Result<()> {
    let max = gpu
        .limits
        .max_storage_buffer_binding_size
        .min(gpu.limits.max_buffer_size);
    if bytes > max {
        return Err(GpuError::TooLarge(format!(
            "{what} needs {bytes} bytes but the adapter ({}) binds at most {max}; render fewer \
             Gaussians or a smaller image, or use the CPU backend",
            gpu.adapter
        )));
    }
    Ok(())
}

/// A storage buffer of `bytes` from `pool`, after checking the device's limits.
pub(super) fn storage_in(
    gpu: &GpuDevice,
    pool: &mut Pool,
    name: &'static str,
    bytes: u64,
) -> Result<wgpu::Buffer> {
    check_binding(gpu, name, bytes)?;
    Ok(pool.get(&gpu.device, name, bytes, STORAGE))
}

/// `data` in a storage buffer from `pool`.
pub(super) fn upload_in<T: bytemuck::Pod>(
    gpu: &GpuDevice,
    pool: &mut Pool,
    name: &'static str,
    data: &[T],
) -> Result<wgpu::Buffer> {
    let bytes = size_of_val(data) as u64;
    let buf = storage_in(gpu, pool, name, bytes)?;
    if bytes > 0 {
        gpu.queue.write_buffer(&buf, 0, bytemuck::cast_slice(data));
    }
    Ok(buf)
}

impl GpuRasterizer {
    pub(super) fn upload<T: bytemuck::Pod>(
        &mut self,
        name: &'static str,
        data: &[T],
    ) -> Result<wgpu::Buffer> {
        upload_in(&self.gpu, &mut self.pool, name, data)
    }

    pub(super) fn storage(&mut self, name: &'static str, bytes: u64) -> Result<wgpu::Buffer> {
        storage_in(&self.gpu, &mut self.pool, name, bytes)
    }

    pub(super) fn uniform<T: bytemuck::Pod>(&self, value: &T) -> wgpu::Buffer {
        self.gpu
            .device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("params"),
                contents: bytemuck::bytes_of(value),
                usage: wgpu::BufferUsages::UNIFORM,
            })
    }

    /// Copy the first `bytes` of `src` to the host.
    pub(super) fn read(&mut self, src: &wgpu::Buffer, bytes: u64) -> Result<Vec<u8>> {
        if bytes == 0 {
            return Ok(Vec::new());
        }
        let staging = self.pool.get(
            &self.gpu.device,
            "staging",
            bytes,
            wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        );
        let mut enc = self
            .gpu
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor::default());
        enc.copy_buffer_to_buffer(src, 0, &staging, 0, bytes);
        self.gpu.queue.submit([enc.finish()]);
        let (tx, rx) = std::sync::mpsc::channel();
        staging.map_async(wgpu::MapMode::Read, ..bytes, move |r| {
            let _ = tx.send(r);
        });
        self.gpu
            .device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| GpuError::Readback(e.to_string()))?;
        rx.recv()
            .map_err(|e| GpuError::Readback(e.to_string()))?
            .map_err(|e| GpuError::Readback(e.to_string()))?;
        let data = staging
            .get_mapped_range(..bytes)
            .map_err(|e| GpuError::Readback(e.to_string()))?
            .to_vec();
        staging.unmap();
        Ok(data)
    }

    pub(super) fn read_f32(&mut self, src: &wgpu::Buffer, count: usize) -> Result<Vec<f32>> {
        Ok(bytemuck::pod_collect_to_vec(
            &self.read(src, count as u64 * 4)?,
        ))
    }
}
