//! The kernels: the WGSL sources, the compositing shader assembled for a layout (template
//! values substituted, sections stripped, loops unrolled), the compiled pipelines (the
//! compositing ones built on first use), and binding and dispatching them. Apart from the
//! rasterizer's stages so that the text processing of the shaders reads, and is tested, on its
//! own.

use std::collections::HashMap;
use std::fmt::Write as _;

use super::layout::BlendLayout;
use super::rasterizer::GpuRasterizer;

const PROJECT_WGSL: &str = include_str!("../shaders/project.wgsl");
const SORT_WGSL: &str = include_str!("../shaders/sort.wgsl");
const SCAN_WGSL: &str = include_str!("../shaders/scan.wgsl");
const BIN_WGSL: &str = include_str!("../shaders/bin.wgsl");
const BLEND_WGSL: &str = include_str!("../shaders/blend.wgsl");
/// The loop check of the kernels llvmpipe may cut short, appended to the modules that use it.
const LOOP_CHECK_WGSL: &str = include_str!("../shaders/loop_check.wgsl");

/// Compiled kernels.
pub(super) struct Kernels {
    pub(super) project: wgpu::ComputePipeline,
    pub(super) project_backward: wgpu::ComputePipeline,
    pub(super) depth_keys: wgpu::ComputePipeline,
    pub(super) radix_count: wgpu::ComputePipeline,
    pub(super) radix_scatter: wgpu::ComputePipeline,
    pub(super) scan_blocks: wgpu::ComputePipeline,
    pub(super) scan_sums: wgpu::ComputePipeline,
    pub(super) scan_add: wgpu::ComputePipeline,
    pub(super) count_corners: wgpu::ComputePipeline,
    pub(super) sum_lines: wgpu::ComputePipeline,
    pub(super) tile_ranges: wgpu::ComputePipeline,
    pub(super) scatter: wgpu::ComputePipeline,
    pub(super) scatter_chunks: wgpu::ComputePipeline,
    /// Compositing kernels by (channel count, column halves, forward), each built on first use
    /// (lavapipe compiles for seconds, and a scene may use halves in one direction only).
    pub(super) blend: HashMap<(usize, bool, bool), wgpu::ComputePipeline>,
}

fn module(dev: &wgpu::Device, label: &str, src: &str) -> wgpu::ShaderModule {
    dev.create_shader_module(wgpu::ShaderModuleDescriptor {
        label: Some(label),
        source: wgpu::ShaderSource::Wgsl(src.into()),
    })
}

fn pipeline(dev: &wgpu::Device, m: &wgpu::ShaderModule, entry: &str) -> wgpu::ComputePipeline {
    dev.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
        label: Some(entry),
        layout: None,
        module: m,
        entry_point: Some(entry),
        compilation_options: wgpu::PipelineCompilationOptions::default(),
        cache: None,
    })
}

impl Kernels {
    pub(super) fn new(dev: &wgpu::Device) -> Self {
        let project = module(dev, "project", PROJECT_WGSL);
        let sort = module(dev, "sort", SORT_WGSL);
        let scan = module(dev, "scan", SCAN_WGSL);
        let bin = module(dev, "bin", &format!("{BIN_WGSL}\n{LOOP_CHECK_WGSL}"));
        Kernels {
            project: pipeline(dev, &project, "project_forward"),
            project_backward: pipeline(dev, &project, "project_backward"),
            depth_keys: pipeline(dev, &sort, "depth_keys"),
            radix_count: pipeline(dev, &sort, "radix_count"),
            radix_scatter: pipeline(dev, &sort, "radix_scatter"),
            scan_blocks: pipeline(dev, &scan, "scan_blocks"),
            scan_sums: pipeline(dev, &scan, "scan_sums"),
            scan_add: pipeline(dev, &scan, "scan_add"),
            count_corners: pipeline(dev, &bin, "count_corners"),
            sum_lines: pipeline(dev, &bin, "sum_lines"),
            tile_ranges: pipeline(dev, &bin, "tile_ranges"),
            scatter: pipeline(dev, &bin, "scatter"),
            scatter_chunks: pipeline(dev, &bin, "scatter_chunks"),
            blend: HashMap::new(),
        }
    }

    /// The forward (else backward) compositing pipeline for `channels` feature channels, the
    /// row blocks split into column halves or not.
    pub(super) fn blend(
        &mut self,
        dev: &wgpu::Device,
        layout: BlendLayout,
        channels: usize,
        halves: bool,
        forward: bool,
    ) -> wgpu::ComputePipeline {
        let key = (channels, halves, forward);
        self.blend
            .entry(key)
            .or_insert_with(|| {
                let m = module(dev, "blend", &layout.shader(channels, halves));
                let rows = layout.block_rows > 0;
                let entry = match (forward, rows, rows && layout.partials) {
                    (true, true, _) => "blend_forward_rows",
                    (true, false, _) => "blend_forward",
                    (false, _, true) => "blend_backward_rows",
                    (false, _, false) => "blend_backward",
                };
                pipeline(dev, &m, entry)
            })
            .clone()
    }
}

impl BlendLayout {
    /// The compositing shader for `channels` channels: template values substituted and the
    /// per-pixel loops (marked `// unroll: pixels`) unrolled, so that every per-pixel array
    /// index is a constant and the arrays live in registers.
    fn shader(&self, channels: usize, halves: bool) -> String {
        let p = self.pixels_per_invocation as usize;
        let stride = channels + 7;
        let invocations = 256 / p;
        let rows = self.block_rows.max(1);
        let halves = if halves { 2 } else { 1 };
        let blocks = halves * 16 / rows as usize;
        // Workgroup memory: 16 KiB guaranteed; the accumulators get up to ~12 KiB.
        let (batch, acc, partial) = if self.subgroup_sums {
            (32, 1, 1)
        } else if self.partials && self.block_rows > 0 {
            // Row blocks: at most 32 splats (one bit each in the block masks).
            let batch = (3072 / (stride * invocations)).clamp(1, 32);
            (batch, 1, batch * stride * invocations)
        } else if self.partials {
            let batch = (3072 / (stride * invocations)).clamp(1, 64);
            (batch, 1, batch * stride * invocations)
        } else {
            let batch = (2048 / stride).clamp(4, 64);
            (batch, batch * stride, 1)
        };
        let mut src = format!("{BLEND_WGSL}\n{LOOP_CHECK_WGSL}");
        if self.block_rows == 0 {
            strip_sections(&mut src, "rows");
        }
        // Subgroup built-ins only compile on devices with the feature: one of the two sections
        // defining the workgroup sums stays.
        strip_sections(
            &mut src,
            if self.subgroup_sums {
                "no-subgroups"
            } else {
                "subgroups"
            },
        );
        strip_sections(
            &mut src,
            if self.float_atomics {
                "no-float-atomics"
            } else {
                "float-atomics"
            },
        );
        let src = src
            .replace(
                "{{GRAD_ATOMIC}}",
                if self.float_atomics { "f32" } else { "u32" },
            )
            .replace(
                "{{SUBGROUP_SUMS}}",
                if self.subgroup_sums { "true" } else { "false" },
            )
            .replace("{{ROWS}}", &rows.to_string())
            .replace("{{HALVES}}", &halves.to_string())
            .replace("{{WALKS}}", &(blocks + usize::from(blocks > 1)).to_string())
            .replace("{{SPANS}}", &stride.div_ceil(invocations).to_string())
            .replace("{{CHANNELS}}", &channels.to_string())
            .replace("{{PIXELS}}", &p.to_string())
            .replace("{{PARTIALS}}", if self.partials { "true" } else { "false" })
            .replace("{{BATCH}}", &batch.to_string())
            .replace("{{ACC}}", &acc.to_string())
            .replace("{{PARTIAL_LEN}}", &partial.to_string());
        let src = unroll_loops(&src, "l", "WG", "lanes", invocations);
        let src = unroll_loops(&src, "c", "C", "channels", channels);
        let src = unroll_loops(&src, "s", "STRIDE", "stride", stride);
        let src = unroll_loops(&src, "h", "SPANS", "spans", stride.div_ceil(invocations));
        let src = unroll_loops(&src, "v", "CV", "feature vectors", channels.div_ceil(4));
        let src = unroll_loops(&src, "w", "NW", "walks", blocks + usize::from(blocks > 1));
        let src = unroll_loops(&src, "b", "NB", "blocks", blocks);
        unroll_loops(&src, "j", "P", "pixels", p)
    }
}

/// Remove every `// <NAME>` ... `// </NAME>` section of `src`.
fn strip_sections(src: &mut String, name: &str) {
    let (open, close) = (format!("// <{name}>\n"), format!("// </{name}>"));
    while let Some(a) = src.find(&open) {
        let b = src[a..].find(&close).expect("blend.wgsl: unclosed section") + a;
        src.replace_range(a..b + close.len(), "");
    }
}

/// Replace every loop `for (var V = 0u; V < N; V++) { // unroll: NAME` ... `}` of `src` by
/// `count` copies of its body ([`push_copies`]). Naga and some drivers (llvmpipe) leave such
/// loops rolled; unrolled, every per-pixel and per-channel array index is a constant and the
/// arrays live in registers instead of scratch memory.
fn unroll_loops(src: &str, var: &str, bound: &str, name: &str, count: usize) -> String {
    // The loop's head up to the body's opening brace, and the tag that follows the brace.
    let head = format!("for (var {var} = 0u; {var} < {bound}; {var}++) ");
    let tag = format!(" // unroll: {name}");
    let mut out = String::with_capacity(src.len() * 2);
    let mut rest = src;
    while let Some(at) = find_tagged(rest, &head, &tag) {
        out.push_str(&rest[..at]);
        let open = at + head.len();
        let end =
            closing_brace(rest, open).expect("blend.wgsl: unbalanced braces in an unrolled loop");
        push_copies(&mut out, var, &rest[open + 1 + tag.len()..end], count);
        rest = &rest[end + 1..];
    }
    out.push_str(rest);
    out
}

/// The byte index of the first `head` in `src` followed, one character (the brace) on, by
/// `tag`.
fn find_tagged(src: &str, head: &str, tag: &str) -> Option<usize> {
    let mut from = 0;
    while let Some(i) = src[from..].find(head) {
        let at = from + i;
        let after = at + head.len() + 1;
        if src.get(after..).is_some_and(|s| s.starts_with(tag)) {
            return Some(at);
        }
        from = at + head.len();
    }
    None
}

/// Append `count` copies of the loop body `body` to `out`, each inside a one-trip loop (so
/// that `continue` keeps its meaning) with `var` a `const` 0, 1, ... (which subgroup broadcasts
/// need as their lane).
fn push_copies(out: &mut String, var: &str, body: &str, count: usize) {
    // A body that jumps (`continue`) stays a loop of one trip; any other is a plain block,
    // which matters on llvmpipe: it caps every shader at 65,535 loop iterations in all
    // (loops end early beyond), and values written in a block need no loop masks.
    let jumps = jumps_out(body);
    for k in 0..count {
        if jumps {
            let _ = writeln!(
                out,
                "for (var once_{var} = 0u; once_{var} < 1u; once_{var}++) {{ const {var} = {k}u;{body}}}"
            );
        } else {
            let _ = writeln!(out, "{{ const {var} = {k}u;{body}}}");
        }
    }
}

/// Whether a loop body holds a `continue` or `break` of its own loop: one outside the loops
/// nested in it (`loop`, `for`, `while` statements, skipped with their bodies).
fn jumps_out(body: &str) -> bool {
    let code: Vec<&str> = body
        .lines()
        .map(|l| l.split("//").next().unwrap_or(""))
        .collect();
    let code = code.join("\n");
    let mut rest = code.as_str();
    loop {
        let nested = ["loop {", "for (", "while "]
            .iter()
            .filter_map(|k| rest.find(k))
            .min();
        let scan_to = nested.unwrap_or(rest.len());
        if rest[..scan_to].contains("continue") || rest[..scan_to].contains("break") {
            return true;
        }
        let Some(at) = nested else { return false };
        // Skip the nested statement: up to its opening brace, then past the matching one.
        let Some(open) = rest[at..].find('{') else {
            return false;
        };
        rest = match closing_brace(rest, at + open) {
            Some(close) => &rest[close + 1..],
            None => "",
        };
    }
}

/// The byte index of the `}` that closes the `{` at byte `open` of `src` (None when unbalanced,
/// or when there is no brace at `open`).
fn closing_brace(src: &str, open: usize) -> Option<usize> {
    let mut depth = 0usize;
    for (i, ch) in src[open..].char_indices() {
        match ch {
            '{' => depth += 1,
            '}' => {
                depth -= 1;
                if depth == 0 {
                    return Some(open + i);
                }
            }
            // No brace at `open`.
            _ if depth == 0 => return None,
            _ => {}
        }
    }
    None
}

/// Workgroup grid for `groups` workgroups of a 1D kernel (2D when beyond the per-dimension
/// limit; the kernels flatten the id).
pub(super) fn grid(groups: u32) -> (u32, u32) {
    let x = groups.clamp(1, 65_535);
    (x, groups.div_ceil(x).max(1))
}

impl GpuRasterizer {
    pub(super) fn bind(
        &self,
        pipe: &wgpu::ComputePipeline,
        buffers: &[(u32, &wgpu::Buffer)],
    ) -> wgpu::BindGroup {
        let entries: Vec<wgpu::BindGroupEntry<'_>> = buffers
            .iter()
            .map(|(b, buf)| wgpu::BindGroupEntry {
                binding: *b,
                resource: buf.as_entire_binding(),
            })
            .collect();
        self.gpu
            .device
            .create_bind_group(&wgpu::BindGroupDescriptor {
                label: None,
                layout: &pipe.get_bind_group_layout(0),
                entries: &entries,
            })
    }

    pub(super) fn dispatch(
        enc: &mut wgpu::CommandEncoder,
        pipe: &wgpu::ComputePipeline,
        group: &wgpu::BindGroup,
        groups: (u32, u32),
    ) {
        let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor::default());
        pass.set_pipeline(pipe);
        pass.set_bind_group(0, group, &[]);
        pass.dispatch_workgroups(groups.0, groups.1, 1);
    }
}

#[cfg(test)]
mod tests {
    use super::{jumps_out, BIN_WGSL, BLEND_WGSL, PROJECT_WGSL, SCAN_WGSL};
    use crate::raster::params::{FIRST_WINDOW, LAST_WINDOW, SCAN_BLOCK, WG};
    use sync4d_raster::project::{COND_MAX, DET_EPS, MAX_RADIUS, QUAT_EPS, RADIUS_SIGMAS};
    use sync4d_raster::TILE_SIZE;

    /// The value of `const name: ty = value;` in a WGSL source, parsed as f64 (a `u` suffix
    /// dropped).
    fn wgsl_const(src: &str, name: &str) -> f64 {
        let head = format!("const {name}: ");
        let line = src
            .lines()
            .find(|l| l.trim_start().starts_with(&head))
            .unwrap_or_else(|| panic!("no `const {name}` in the shader"));
        let value = line.split('=').nth(1).expect("a value").split(';').next();
        let value = value.expect("a `;`").trim().trim_end_matches('u');
        value
            .parse()
            .unwrap_or_else(|e| panic!("const {name} = {value}: {e}"))
    }

    /// The shaders' copies of host constants (WGSL has no way to import them) agree with their
    /// one home: sync4d-raster for the rasterizer's geometry, `params` for the kernels'
    /// interface. Floats are compared after rounding the home value to f32, as the kernels
    /// read them.
    #[test]
    fn shader_constants_match_their_host_home() {
        let f32_of = |v: f64| f64::from(v as f32);
        assert_eq!(wgsl_const(BIN_WGSL, "TILE"), f64::from(TILE_SIZE));
        for (name, home) in [
            ("RADIUS_SIGMAS", RADIUS_SIGMAS),
            ("QUAT_EPS", QUAT_EPS),
            ("DET_EPS", DET_EPS),
            ("MAX_RADIUS", MAX_RADIUS),
            ("COND_MAX", COND_MAX),
        ] {
            assert_eq!(
                f32_of(wgsl_const(PROJECT_WGSL, name)),
                f32_of(home),
                "{name}"
            );
        }
        assert_eq!(wgsl_const(SCAN_WGSL, "WG"), f64::from(WG));
        assert_eq!(wgsl_const(SCAN_WGSL, "BLOCK"), f64::from(SCAN_BLOCK));
        assert_eq!(
            wgsl_const(BLEND_WGSL, "FIRST_WINDOW"),
            f64::from(FIRST_WINDOW)
        );
        assert_eq!(
            wgsl_const(BLEND_WGSL, "LAST_WINDOW"),
            f64::from(LAST_WINDOW)
        );
    }

    /// The f32 compositing thresholds sent to the kernels are the values the GPU path used
    /// before they had one home (`1.0 / 255.0` and `1e-4` as f32 literals).
    #[test]
    fn thresholds_round_to_the_former_f32_literals() {
        assert_eq!(
            (sync4d_raster::ALPHA_MIN as f32).to_bits(),
            (1.0f32 / 255.0).to_bits()
        );
        assert_eq!((sync4d_raster::T_MIN as f32).to_bits(), 1e-4f32.to_bits());
    }

    #[test]
    fn jumps_out_sees_only_the_bodys_own_jumps() {
        assert!(jumps_out("if a { continue; }"));
        assert!(jumps_out("x = 1; break;"));
        assert!(!jumps_out("loop { if a { break; } }"));
        assert!(!jumps_out(
            "for (var i = 0u; i < 3u; i++) { continue; } y = 2;"
        ));
        assert!(jumps_out("loop { break; } if b { continue; }"));
        // Comments are not code.
        assert!(!jumps_out("// break while we can\nx = 1;"));
        assert!(jumps_out("// loop { over\nbreak;"));
    }
}
