//! Per-stage profiling of the rasterizer: while it is on, every stage is submitted on its own
//! and waited for, and its wall time booked under the stage's name. Apart from the stages,
//! which only mark where they end.

use super::rasterizer::GpuRasterizer;

/// Stage timings of the calls made while profiling: (stage name, seconds), in call order.
#[derive(Debug, Default)]
pub(super) struct Profile {
    pub(super) since: Option<std::time::Instant>,
    stages: Vec<(&'static str, f64)>,
}

impl GpuRasterizer {
    /// Time every stage of the following calls (projection, depth sort, binning, scatter,
    /// compositing, ...): each stage is submitted on its own and waited for, which costs some
    /// overlap, so use it to find where time goes, not to measure the total.
    pub fn set_profiling(&mut self, on: bool) {
        self.profile = on.then(Profile::default);
    }

    /// The (stage, seconds) timings recorded since the last call, in order; empty when
    /// profiling is off.
    pub fn take_profile(&mut self) -> Vec<(&'static str, f64)> {
        self.profile
            .as_mut()
            .map(|p| std::mem::take(&mut p.stages))
            .unwrap_or_default()
    }

    /// When profiling: submit `enc`, wait for the device and book the time since the previous
    /// mark to `stage`; `enc` continues as a fresh encoder.
    pub(super) fn mark(&mut self, enc: &mut wgpu::CommandEncoder, stage: &'static str) {
        let Some(p) = self.profile.as_mut() else {
            return;
        };
        let done = std::mem::replace(
            enc,
            self.gpu
                .device
                .create_command_encoder(&wgpu::CommandEncoderDescriptor::default()),
        );
        self.gpu.queue.submit([done.finish()]);
        let _ = self.gpu.device.poll(wgpu::PollType::wait_indefinitely());
        let now = std::time::Instant::now();
        if let Some(t0) = p.since {
            p.stages.push((stage, (now - t0).as_secs_f64()));
        }
        p.since = Some(now);
    }

    /// When profiling: book host-side work since the previous mark to `stage`.
    pub(super) fn mark_host(&mut self, stage: &'static str) {
        if let Some(p) = self.profile.as_mut() {
            let now = std::time::Instant::now();
            if let Some(t0) = p.since {
                p.stages.push((stage, (now - t0).as_secs_f64()));
            }
            p.since = Some(now);
        }
    }
}
