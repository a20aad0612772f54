//! Adapter selection: which GPU (or CPU Vulkan driver such as lavapipe) runs the kernels.

use crate::error::{GpuError, Result};

/// Which kind of adapter to use.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AdapterChoice {
    /// The best adapter there is: a discrete GPU, else an integrated one, else a virtual one,
    /// else a CPU driver (lavapipe).
    Auto,
    /// A hardware (or virtual) GPU only; an error when there is none.
    Gpu,
    /// A CPU implementation only (lavapipe / SwiftShader); an error when there is none.
    Cpu,
}

impl std::str::FromStr for AdapterChoice {
    type Err = GpuError;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "auto" => Ok(AdapterChoice::Auto),
            "gpu" => Ok(AdapterChoice::Gpu),
            "cpu" => Ok(AdapterChoice::Cpu),
            other => Err(GpuError::NoAdapter(format!(
                "unknown adapter choice '{other}' (expected auto, gpu or cpu)"
            ))),
        }
    }
}

/// What an adapter is, in words a user recognises.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct AdapterSummary {
    /// Driver-reported device name, e.g. "llvmpipe (LLVM 15.0.6, 256 bits)".
    pub name: String,
    /// "discrete", "integrated", "virtual", "cpu" or "other".
    pub kind: &'static str,
    /// Graphics API, e.g. "Vulkan", "Metal", "Dx12".
    pub backend: String,
    /// Driver name and version as reported.
    pub driver: String,
}

impl std::fmt::Display for AdapterSummary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{} ({}, {}", self.name, self.kind, self.backend)?;
        if !self.driver.is_empty() {
            write!(f, ", {}", self.driver)?;
        }
        write!(f, ")")
    }
}

fn kind_of(t: wgpu::DeviceType) -> &'static str {
    match t {
        wgpu::DeviceType::DiscreteGpu => "discrete",
        wgpu::DeviceType::IntegratedGpu => "integrated",
        wgpu::DeviceType::VirtualGpu => "virtual",
        wgpu::DeviceType::Cpu => "cpu",
        wgpu::DeviceType::Other => "other",
    }
}

/// Preference order of `Auto` (lower is better).
fn rank(t: wgpu::DeviceType) -> u8 {
    match t {
        wgpu::DeviceType::DiscreteGpu => 0,
        wgpu::DeviceType::IntegratedGpu => 1,
        wgpu::DeviceType::VirtualGpu => 2,
        wgpu::DeviceType::Other => 3,
        wgpu::DeviceType::Cpu => 4,
    }
}

fn summary(info: &wgpu::AdapterInfo) -> AdapterSummary {
    AdapterSummary {
        name: info.name.clone(),
        kind: kind_of(info.device_type),
        backend: format!("{:?}", info.backend),
        driver: format!("{} {}", info.driver, info.driver_info)
            .trim()
            .to_string(),
    }
}

fn instance() -> wgpu::Instance {
    let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
    desc.backends = wgpu::Backends::PRIMARY;
    wgpu::Instance::new(desc)
}

/// Every adapter wgpu finds on this machine (Vulkan, Metal, DX12), best first.
pub fn list_adapters() -> Vec<AdapterSummary> {
    let mut infos: Vec<wgpu::AdapterInfo> =
        pollster::block_on(instance().enumerate_adapters(wgpu::Backends::PRIMARY))
            .iter()
            .map(wgpu::Adapter::get_info)
            .collect();
    infos.sort_by_key(|i| rank(i.device_type));
    infos.iter().map(summary).collect()
}

/// An opened device and queue on the chosen adapter.
pub struct GpuDevice {
    /// The wgpu device.
    pub device: wgpu::Device,
    /// Its queue.
    pub queue: wgpu::Queue,
    /// The adapter it runs on.
    pub adapter: AdapterSummary,
    /// Limits granted to the device.
    pub limits: wgpu::Limits,
    /// The smallest subgroup the adapter may run (8 on 256-bit lavapipe), when the device was
    /// opened with subgroup operations (wgpu's `SUBGROUP` feature); `None` without them.
    pub subgroup_min_size: Option<u32>,
    /// Whether the device adds `f32` values to storage buffers atomically (wgpu's
    /// `SHADER_FLOAT32_ATOMIC`: lavapipe and most Vulkan GPUs), used for the backward's
    /// per-splat gradient sums instead of compare-and-swap loops.
    pub float_atomics: bool,
}

impl GpuDevice {
    /// Open a device on the adapter `choice` picks. Errors (never hangs or panics) when no
    /// adapter fits, naming what was found and what to install.
    pub fn new(choice: AdapterChoice) -> Result<Self> {
        let inst = instance();
        let mut adapters = pollster::block_on(inst.enumerate_adapters(wgpu::Backends::PRIMARY));
        adapters.sort_by_key(|a| rank(a.get_info().device_type));
        let found: Vec<String> = adapters
            .iter()
            .map(|a| summary(&a.get_info()).to_string())
            .collect();
        let pick = adapters.into_iter().find(|a| {
            let t = a.get_info().device_type;
            match choice {
                AdapterChoice::Auto => true,
                AdapterChoice::Gpu => t != wgpu::DeviceType::Cpu,
                AdapterChoice::Cpu => t == wgpu::DeviceType::Cpu,
            }
        });
        let Some(adapter) = pick else {
            let what = match choice {
                AdapterChoice::Auto => "no Vulkan, Metal or DX12 adapter",
                AdapterChoice::Gpu => "no GPU adapter",
                AdapterChoice::Cpu => "no CPU (lavapipe) adapter",
            };
            let seen = if found.is_empty() {
                "none".to_string()
            } else {
                found.join("; ")
            };
            return Err(GpuError::NoAdapter(format!(
                "{what} found (adapters seen: {seen}); on Debian/Ubuntu install \
                 mesa-vulkan-drivers and libvulkan1 for lavapipe, or use the CPU backend"
            )));
        };
        let limits = adapter.limits();
        let info = adapter.get_info();
        let features =
            adapter.features() & (wgpu::Features::SUBGROUP | wgpu::Features::SHADER_FLOAT32_ATOMIC);
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("sync4d"),
            required_features: features,
            required_limits: limits.clone(),
            ..Default::default()
        }))
        .map_err(|e| GpuError::Device(e.to_string()))?;
        Ok(GpuDevice {
            device,
            queue,
            adapter: summary(&info),
            limits,
            subgroup_min_size: features
                .contains(wgpu::Features::SUBGROUP)
                .then_some(info.subgroup_min_size),
            float_atomics: features.contains(wgpu::Features::SHADER_FLOAT32_ATOMIC),
        })
    }
}
