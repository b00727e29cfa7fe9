//! The scalar far field in f64: each line swept against the look direction keeping the upper
//! convex hull of its samples (blocked hulls for a finite radius), each texel's tangent asked of
//! the two lines beside it. The path on CPUs without AVX-512, and the oracle the vector far
//! field (`vector`, `avx512`) is tested against.

use super::*;

/// A hull vertex: major position and height (less the curvature term).
pub(super) type Pt = (f64, f64);

/// Fills `out` (W·H, texel-major) with the far field's tan α of every texel along `lines`:
/// the tangents of the two sub-lines on either side of the texel, interpolated by its place
/// between them (their lateral error cancels to first order). `wsum` is scratch (W·H).
pub(super) fn far_field(
    grid: &Grid<'_>,
    lines: Lines,
    reach: Option<f64>,
    curv: f64,
    out: &mut [f32],
    wsum: &mut Vec<f32>,
) {
    let (w, h) = (grid.width, grid.height);
    let (wa, hb) = if lines.major_x { (w, h) } else { (h, w) };
    // Steps within R, and where the far field starts.
    let r_steps = reach.map(|r| (r / lines.step + 1e-9).floor() as i64);
    let d = NEAR_STEPS as i64;
    if r_steps.is_some_and(|r| r < d) {
        return;
    }
    wsum.clear();
    wsum.resize(w * h, 0.0);
    let wrap = grid.edge == Edge::Wrap;
    // Samples run over u' in 0..len (beyond the map when wrapping).
    let len = match (wrap, r_steps) {
        (true, Some(r)) => wa as i64 + r,
        _ => wa as i64,
    };
    let cc = curv * lines.step * lines.step;
    let major = |u: i64| -> i64 {
        let u = if wrap { u.rem_euclid(wa as i64) } else { u };
        if lines.sign > 0 {
            u
        } else {
            wa as i64 - 1 - u
        }
    };
    // Tables so the sweeps do no division: each column's image offset of minor 0, the step
    // of one minor texel.
    let abase: Vec<usize> = (0..len)
        .map(|u| {
            let a = major(u) as usize;
            if lines.major_x {
                a
            } else {
                a * w
            }
        })
        .collect();
    let mstep = if lines.major_x { w } else { 1 };
    let hbi = hb as i64;
    // Per query column, the two sub-lines around its texels: (family, shift, weight) each.
    let fams: Vec<[(usize, i64, f64); 2]> = (0..wa as i64).map(|u| lines.pair(u)).collect();
    let (sh_lo, sh_hi) = fams
        .iter()
        .flatten()
        .fold((i64::MAX, i64::MIN), |(lo, hi), &(_, s, _)| (lo.min(s), hi.max(s)));
    let hs = grid.heights;
    let fams: Vec<[(usize, i64, f64); 2]> = if wrap {
        fams.iter().map(|p| p.map(|(k, sh, wt)| (k, sh.rem_euclid(hbi), wt))).collect()
    } else {
        fams
    };
    let mut samples: Vec<(i64, f64)> = Vec::with_capacity(len as usize);
    let mut mids: Vec<(i64, f64)> = Vec::with_capacity(len as usize);
    let mut hull: Vec<Pt> = Vec::new();
    // Per column and role (lower, upper line): the best slope found (NaN: none yet).
    let mut best: Vec<[f64; 2]> = vec![[f64::NAN; 2]; wa];
    for k in 0..SUB {
        samples.clear();
        // Minor offsets reduced modulo the map when wrapping (the line index adds < hb).
        let reduce = |(off, wt): (i64, f64)| (if wrap { off.rem_euclid(hbi) } else { off }, wt);
        samples.extend((0..len).map(|u| reduce(lines.sample(k, u))));
        mids.clear();
        mids.extend((0..len).map(|u| reduce(lines.sample_at(k, u as f64 + 0.5))));
        // Lines i whose texels b = i − shift lie in the map (all of them when wrapping).
        let (i_lo, i_hi) = if wrap { (0, hb as i64 - 1) } else { (sh_lo, hb as i64 - 1 + sh_hi) };
        for i in i_lo..=i_hi {
            // The line's value at column a, minor lerp (off, wt) (None: off the surface).
            // The line's value at column u, minor lerp (off, wt) (None: off the surface).
            let lerp = |u: i64, (off, wt): (i64, f64)| -> Option<f64> {
                let base = abase[u as usize];
                let b = i + off;
                if wrap {
                    // 0 ≤ i < hb and 0 ≤ off < hb.
                    let b0 = if b >= hbi { b - hbi } else { b };
                    let b1 = if b0 + 1 == hbi { 0 } else { b0 + 1 };
                    let h0 = hs[base + b0 as usize * mstep] as f64;
                    let h1 = hs[base + b1 as usize * mstep] as f64;
                    Some(h0 + (h1 - h0) * wt)
                } else if b >= 0 && b + 1 < hbi {
                    let h0 = hs[base + b as usize * mstep] as f64;
                    let h1 = hs[base + (b + 1) as usize * mstep] as f64;
                    Some(h0 + (h1 - h0) * wt)
                } else if b == hbi - 1 && wt == 0.0 {
                    Some(hs[base + b as usize * mstep] as f64)
                } else {
                    None
                }
            };
            let sample = |u: i64| lerp(u, samples[u as usize]);
            // Halfway between grid lines u and u + 1: the bulge of the cells between them.
            let mid = |u: i64| -> Option<f64> {
                if !MIDS || u + 1 >= len {
                    return None;
                }
                let m = mids[u as usize];
                Some(0.5 * (lerp(u, m)? + lerp(u + 1, m)?))
            };
            let g = |x: f64, v: f64| (x, v - cc * x * x);
            // The texel of column u for which this line is role r (0: the line below it, 1:
            // above), with its height and weight.
            let texel = |u: i64, r: usize| -> Option<(usize, f64, f64)> {
                let (fk, shift, wt) = fams[u as usize][r];
                if fk != k {
                    return None;
                }
                let b = i - shift;
                let b = if wrap {
                    // Shifts are stored modulo hb when wrapping (see `fams`).
                    if b < 0 {
                        b + hbi
                    } else {
                        b
                    }
                } else if (0..hbi).contains(&b) {
                    b
                } else {
                    return None;
                };
                let t = abase[u as usize] + b as usize * mstep;
                Some((t, hs[t] as f64, wt))
            };
            let mut any = false;
            let mut ask = |q: i64, hull: &[Pt], left: bool, best: &mut Vec<[f64; 2]>| {
                for (r, b) in best[q as usize].iter_mut().enumerate() {
                    if let Some((_, h0, _)) = texel(q, r) {
                        let s = if left {
                            tangent_left(hull, q, h0, cc)
                        } else {
                            tangent_right(hull, q, h0, cc)
                        };
                        if let Some(s) = s {
                            // NaN (nothing yet) or smaller: take s.
                            if b.is_nan() || *b < s {
                                *b = s;
                            }
                            any = true;
                        }
                    }
                }
            };
            for b in best.iter_mut() {
                *b = [f64::NAN; 2];
            }
            match r_steps {
                None => {
                    // One plain hull, right to left.
                    hull.clear();
                    for up in (d..len).rev() {
                        if let Some(v) = mid(up) {
                            push_left(&mut hull, g(up as f64 + 0.5, v));
                        }
                        if let Some(v) = sample(up) {
                            push_left(&mut hull, g(up as f64, v));
                        }
                        ask(up - d, &hull, true, &mut best);
                    }
                }
                Some(r) => {
                    let blk = r - d + 1;
                    hull.clear();
                    for up in (d..len).rev() {
                        if up % blk == blk - 1 {
                            hull.clear();
                        } else if let Some(v) = mid(up) {
                            // (A block's last midpoint would lie past R for some queries: the
                            // prefix pass has it.)
                            push_left(&mut hull, g(up as f64 + 0.5, v));
                        }
                        if let Some(v) = sample(up) {
                            push_left(&mut hull, g(up as f64, v));
                        }
                        if up - d < wa as i64 {
                            ask(up - d, &hull, true, &mut best);
                        }
                    }
                    // Prefix hulls, left to right: the window's part in the next block.
                    hull.clear();
                    let mut next = d; // next sample to push
                    for q in 0..wa as i64 {
                        let top = (q + r).min(len - 1);
                        while next <= top {
                            if next % blk == 0 {
                                hull.clear();
                            }
                            // With the midpoint before a block's first sample, which the
                            // suffix pass leaves out.
                            if next > d {
                                if let Some(v) = mid(next - 1) {
                                    push_right(&mut hull, g(next as f64 - 0.5, v));
                                }
                            }
                            if let Some(v) = sample(next) {
                                push_right(&mut hull, g(next as f64, v));
                            }
                            next += 1;
                        }
                        // Only when the window reaches into the next block: otherwise the
                        // suffix pass saw all of it, and this hull may hold samples nearer than
                        // q + d (at the map's end, where q + r is clipped).
                        if top / blk > (q + d) / blk {
                            ask(q, &hull, false, &mut best);
                        }
                    }
                }
            }
            if !any {
                continue;
            }
            for (q, pair) in best.iter().enumerate() {
                for (r, &s) in pair.iter().enumerate() {
                    if s.is_nan() {
                        continue;
                    }
                    if let Some((t, _, wt)) = texel(q as i64, r) {
                        out[t] += (wt * s / lines.step) as f32;
                        wsum[t] += wt as f32;
                    }
                }
            }
        }
    }
    for (o, &ws) in out.iter_mut().zip(wsum.iter()) {
        // One of the two lines may have nothing ahead (off the surface): the other alone.
        *o = if ws > 0.0 { *o / ws } else { 0.0 };
    }
}

/// Pushes `p` (left of every vertex) onto the upper hull `hull` (nearest vertex last).
#[inline]
pub(super) fn push_left(hull: &mut Vec<Pt>, p: Pt) {
    while hull.len() >= 2 {
        let t1 = hull[hull.len() - 1];
        let t2 = hull[hull.len() - 2];
        // Keep t1 only if the slope p→t1 is above t1→t2.
        if (t1.1 - p.1) * (t2.0 - t1.0) > (t2.1 - t1.1) * (t1.0 - p.0) {
            break;
        }
        hull.pop();
    }
    hull.push(p);
}

/// Pushes `p` (right of every vertex) onto the upper hull `hull` (farthest vertex last).
#[inline]
pub(super) fn push_right(hull: &mut Vec<Pt>, p: Pt) {
    while hull.len() >= 2 {
        let t1 = hull[hull.len() - 1];
        let t2 = hull[hull.len() - 2];
        // Keep t1 only if the slope t2→t1 is above t1→p.
        if (t1.1 - t2.1) * (p.0 - t1.0) > (p.1 - t1.1) * (t1.0 - t2.0) {
            break;
        }
        hull.pop();
    }
    hull.push(p);
}

/// The query point of major position `q`, height `h0`, on the hulls of g = h − cc·u², and the
/// slope correction (see the module doc): slope to the hull + 2·cc·q.
#[inline]
pub(super) fn origin(q: i64, h0: f64, cc: f64) -> (f64, f64, f64) {
    let x = q as f64;
    (x, h0 - cc * x * x, 2.0 * cc * x)
}

/// The largest slope from (q, h0) to a vertex of `hull` (nearest vertex last), per major step:
/// the slopes are unimodal along the hull, so a galloping search from the nearest vertex finds
/// the tangent in O(log d) steps for a tangent d vertices away (a far horizon on a long concave
/// hull would make a plain walk O(d)).
#[inline]
pub(super) fn tangent_left(hull: &[Pt], q: i64, h0: f64, cc: f64) -> Option<f64> {
    let n = hull.len();
    if n == 0 {
        return None;
    }
    let (x, y, corr) = origin(q, h0, cc);
    let f = |j: usize| {
        let p = hull[n - 1 - j];
        (p.1 - y) / (p.0 - x)
    };
    // Rising at j: the next vertex (farther) has the larger slope.
    let rising = |j: usize| j + 1 < n && f(j + 1) > f(j);
    let (mut lo, mut hi) = (0usize, 1usize);
    while hi < n && rising(hi) {
        lo = hi + 1;
        hi *= 2;
    }
    let mut hi = hi.min(n - 1);
    lo = lo.min(hi);
    // The first j in lo..=hi that is not rising.
    while lo < hi {
        let mid = (lo + hi) / 2;
        if rising(mid) {
            lo = mid + 1;
        } else {
            hi = mid;
        }
    }
    Some(f(lo) + corr)
}

/// The largest slope from (q, h0) to a vertex of `hull` (farthest vertex last): binary search
/// of the unimodal slopes.
#[inline]
pub(super) fn tangent_right(hull: &[Pt], q: i64, h0: f64, cc: f64) -> Option<f64> {
    if hull.is_empty() {
        return None;
    }
    let (x, y, corr) = origin(q, h0, cc);
    let slope = |p: Pt| (p.1 - y) / (p.0 - x);
    let (mut lo, mut hi) = (0usize, hull.len() - 1);
    while lo < hi {
        let mid = (lo + hi) / 2;
        if slope(hull[mid + 1]) > slope(hull[mid]) {
            lo = mid + 1;
        } else {
            hi = mid;
        }
    }
    Some(slope(hull[lo]) + corr)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The hull tangents against brute force over the same points.
    #[test]
    fn hull_tangents_match_brute_force() {
        let mut seed = 12345u64;
        let mut rnd = || {
            seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((seed >> 33) as f64 / (1u64 << 31) as f64) * 10.0 - 5.0
        };
        for &cc in &[0.0, 0.01] {
            let pts: Vec<Pt> = (0..200).map(|u| (u as f64, rnd() - cc * (u * u) as f64)).collect();
            let raw = |u: usize| pts[u].1 + cc * (u * u) as f64;
            for q in 0..150i64 {
                let h0 = rnd();
                let from = (q + 3) as usize;
                let mut left = Vec::new();
                for u in (from..200).rev() {
                    push_left(&mut left, pts[u]);
                }
                let mut right = Vec::new();
                for p in &pts[from..200] {
                    push_right(&mut right, *p);
                }
                let want = (from..200)
                    .map(|u| {
                        let s = (u as i64 - q) as f64;
                        (raw(u) - cc * s * s - h0) / s
                    })
                    .fold(f64::NEG_INFINITY, f64::max);
                let a = tangent_left(&left, q, h0, cc).unwrap();
                let b = tangent_right(&right, q, h0, cc).unwrap();
                assert!((a - want).abs() < 1e-9, "{a} {want}");
                assert!((b - want).abs() < 1e-9, "{b} {want}");
            }
        }
    }
}
