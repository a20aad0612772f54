//! Plain f64 reference compositor: a brute-force loop per pixel over every visible splat in
//! (depth, index) order, with the same rules as the tiled fast path (alpha clamp, 1/255 skip,
//! transmittance stop) but no tiles, no boxes, no batching and no threads. Tests compare the
//! fast path against it, and the torch op uses it for float64 inputs (gradcheck).
//!
//! Tile culling in the fast path is lossless (the screen radius bounds every pixel where
//! alpha >= 1/255), so both compute the same function.

use crate::blend::{
    BlendSettings, Counters, ImageGrads, ImageMut, SplatGradsMut, Splats, ALPHA_MIN, T_MIN,
};
use crate::error::Result;

/// Visible splats sorted by (depth, index).
fn depth_order(sp: &Splats<'_, f64>) -> Vec<usize> {
    let mut order: Vec<usize> = (0..sp.len())
        .filter(|&g| sp.radii[2 * g] > 0 && sp.radii[2 * g + 1] > 0)
        .collect();
    order.sort_by(|&a, &b| sp.depths[a].total_cmp(&sp.depths[b]).then(a.cmp(&b)));
    order
}

/// Alpha of splat `g` at pixel centre `(x + 0.5, y + 0.5)` with its intermediates
/// `(alpha, unclamped alpha, exp(-sigma), dx, dy)`, or `None` when the splat is skipped there.
fn alpha_at(
    sp: &Splats<'_, f64>,
    g: usize,
    x: u32,
    y: u32,
    alpha_max: f64,
) -> Option<(f64, f64, f64, f64, f64)> {
    let dx = x as f64 + 0.5 - sp.means2d[2 * g];
    let dy = y as f64 + 0.5 - sp.means2d[2 * g + 1];
    let (a, b, c) = (sp.conics[3 * g], sp.conics[3 * g + 1], sp.conics[3 * g + 2]);
    let sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy;
    // NaN-safe, as in the fast path: a NaN sigma (inf - inf for huge conics) would otherwise
    // give alpha = NaN.min(alpha_max) = alpha_max.
    if sigma.is_nan() || sigma < 0.0 {
        return None;
    }
    let vis = (-sigma).exp();
    let raw = sp.opacities[g] * vis;
    let alpha = raw.min(alpha_max);
    (alpha >= ALPHA_MIN).then_some((alpha, raw, vis, dx, dy))
}

/// The splats composited at pixel (x, y), front to back, with their alphas.
fn pixel_contributors(
    sp: &Splats<'_, f64>,
    order: &[usize],
    x: u32,
    y: u32,
    alpha_max: f64,
    evaluated: &mut u64,
) -> Vec<(usize, f64)> {
    let mut t = 1.0;
    let mut out = Vec::new();
    for &g in order {
        *evaluated += 1;
        let Some((alpha, ..)) = alpha_at(sp, g, x, y, alpha_max) else {
            continue;
        };
        let next_t = t * (1.0 - alpha);
        if next_t < T_MIN {
            break;
        }
        out.push((g, alpha));
        t = next_t;
    }
    out
}

/// Reference forward: same outputs as [`crate::blend::rasterize_forward`], in f64.
pub fn rasterize_forward_reference(
    sp: &Splats<'_, f64>,
    width: u32,
    height: u32,
    background: &[f64],
    settings: &BlendSettings,
    out: ImageMut<'_, f64>,
) -> Result<Counters> {
    sp.validate(background)?;
    settings.validate()?;
    crate::blend::check_image_size(width, height)?;
    let ch = sp.channels;
    let npix = (width * height) as usize;
    out.check_len(npix, ch)?;
    let order = depth_order(sp);
    let mut counters = Counters {
        visible: order.len() as u64,
        ..Default::default()
    };
    for y in 0..height {
        for x in 0..width {
            let pix = (y * width + x) as usize;
            let list = pixel_contributors(
                sp,
                &order,
                x,
                y,
                settings.alpha_max,
                &mut counters.evaluated,
            );
            counters.blended += list.len() as u64;
            let mut t = 1.0;
            let mut acc = vec![0.0; ch];
            let mut depth = 0.0;
            for &(g, alpha) in &list {
                let w = alpha * t;
                for c in 0..ch {
                    acc[c] += sp.features[g * ch + c] * w;
                }
                depth += sp.depths[g] * w;
                t *= 1.0 - alpha;
            }
            for c in 0..ch {
                out.features[pix * ch + c] = acc[c] + t * background[c];
            }
            out.alpha[pix] = 1.0 - t;
            out.depth[pix] = depth;
        }
    }
    Ok(counters)
}

/// Reference backward of [`rasterize_forward_reference`], in f64: recomputes each pixel's
/// contributors and differentiates the composite directly (forward products, no division).
///
/// # Panics
/// Only on an internal inconsistency: a pixel's recorded contributor no longer passing the
/// alpha test with the same inputs.
pub fn rasterize_backward_reference(
    sp: &Splats<'_, f64>,
    width: u32,
    height: u32,
    background: &[f64],
    settings: &BlendSettings,
    v: &ImageGrads<'_, f64>,
    grads: SplatGradsMut<'_, f64>,
) -> Result<()> {
    sp.validate(background)?;
    settings.validate()?;
    let ch = sp.channels;
    let n = sp.len();
    let npix = (width * height) as usize;
    v.validate(npix, ch)?;
    grads.check_len(n, ch)?;
    for buf in [
        &mut *grads.means2d,
        &mut *grads.conics,
        &mut *grads.depths,
        &mut *grads.opacities,
        &mut *grads.features,
    ] {
        buf.fill(0.0);
    }
    let order = depth_order(sp);
    let mut evaluated = 0;
    for y in 0..height {
        for x in 0..width {
            let pix = (y * width + x) as usize;
            let list = pixel_contributors(sp, &order, x, y, settings.alpha_max, &mut evaluated);
            let k = list.len();
            // Transmittance before each contributor, and the final one.
            let mut ts = Vec::with_capacity(k + 1);
            let mut t = 1.0;
            for &(_, alpha) in &list {
                ts.push(t);
                t *= 1.0 - alpha;
            }
            let t_final = t;
            // Feature vector of splat g with the depth channel appended, and its upstream grad.
            let feat = |g: usize, c: usize| {
                if c < ch {
                    sp.features[g * ch + c]
                } else {
                    sp.depths[g]
                }
            };
            let vc = |c: usize| {
                if c < ch {
                    v.features[pix * ch + c]
                } else {
                    v.depth[pix]
                }
            };
            let bg = |c: usize| if c < ch { background[c] } else { 0.0 };
            for (i, &(g, alpha)) in list.iter().enumerate() {
                let ti = ts[i];
                // d out_c / d alpha_i = f_ic T_i - (sum_{j>i} f_jc a_j T_j + T_N bg_c) / (1 - a_i)
                // d alpha_out / d alpha_i = T_N / (1 - a_i)
                let mut v_alpha = v.alpha[pix] * t_final / (1.0 - alpha);
                for c in 0..=ch {
                    let mut behind = t_final * bg(c);
                    for (j, &(h, aj)) in list.iter().enumerate().skip(i + 1) {
                        behind += feat(h, c) * aj * ts[j];
                    }
                    v_alpha += vc(c) * (feat(g, c) * ti - behind / (1.0 - alpha));
                    let w = alpha * ti;
                    if c < ch {
                        grads.features[g * ch + c] += vc(c) * w;
                    } else {
                        grads.depths[g] += vc(c) * w;
                    }
                }
                let (_, raw, vis, dx, dy) =
                    alpha_at(sp, g, x, y, settings.alpha_max).expect("contributor");
                if raw > settings.alpha_max {
                    continue;
                }
                grads.opacities[g] += v_alpha * vis;
                let v_sigma = -v_alpha * alpha;
                let (a, b, c) = (sp.conics[3 * g], sp.conics[3 * g + 1], sp.conics[3 * g + 2]);
                grads.conics[3 * g] += 0.5 * v_sigma * dx * dx;
                grads.conics[3 * g + 1] += v_sigma * dx * dy;
                grads.conics[3 * g + 2] += 0.5 * v_sigma * dy * dy;
                grads.means2d[2 * g] -= v_sigma * (a * dx + b * dy);
                grads.means2d[2 * g + 1] -= v_sigma * (c * dy + b * dx);
            }
        }
    }
    Ok(())
}
