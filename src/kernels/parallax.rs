//! The parallax family (SPEC §3.5): where on the height map a pixel of the flat surface really
//! looks, given the view direction.
//!
//! All methods work in texel units on the same scaled heights as the bake, so `strength` = 1 is
//! the true relief of the map (0 turns parallax off). V is the unit tangent-space direction from
//! the surface toward the eye, already turned into image-plane components (columns, rows, z) by
//! the caller; q(t) = p − t·V.xy/V.z is where the eye ray through p sits at depth t below the
//! reference plane.
//!
//! - `offset` (Kaneko/Welsh with the common 0.42 bias, as Unity's `ParallaxOffset`): one height
//!   fetch, reference plane at mid height: p + strength·(h(p) − h_mid)·V.xy / (V.z + 0.42).
//! - `offset_limited` (Welsh 2004): the same without the division, so the offset never exceeds
//!   the height: p + strength·(h(p) − h_mid)·V.xy.
//! - `steep` (McGuire & McGuire 2005, "steep parallax"): reference plane at the top of the relief;
//!   march `steps` equal depth layers down to the bottom and stop at the first layer below the
//!   surface.
//! - `interpolated` (parallax occlusion mapping, Tatarchuk 2006): `steep`, then the linear
//!   intersection of the ray with the surface between the last two layers.
//! - `relief` (Policarpo et al. 2005): `steep`, then `search_steps` bisections of that bracket.
//!
//! The depth of the surface at q is strength·(h_max − h(q)); the ray's depth at layer i is
//! i·D/steps with D = strength·(h_max − h_min), so the march always ends on or below the surface.
//! V.z is floored at 1e-3 so grazing views stay finite.

/// Which parallax method.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Parallax {
    None,
    Offset,
    OffsetLimited,
    Steep,
    Interpolated,
    Relief,
}

/// Parameters of a parallax method.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ParallaxSettings {
    pub method: Parallax,
    /// Depth layers of the steep family (≥ 1).
    pub steps: u32,
    /// Bisections of `relief`.
    pub search_steps: u32,
    /// Multiplier of the relief depth (1 = the map's true heights in texels).
    pub strength: f64,
}

/// The common bias of the plain offset method.
pub const OFFSET_BIAS: f64 = 0.42;

/// The displaced texel coordinate for pixel position `p` (image coordinates, texel centres at
/// integers), view `v` = (columns, rows, z) unit with z > 0, heights `height(x, r)` in texels
/// spanning [`hmin`, `hmax`].
pub fn displace<H: Fn(f64, f64) -> f64>(
    height: H,
    hmin: f64,
    hmax: f64,
    p: (f64, f64),
    v: [f64; 3],
    s: &ParallaxSettings,
) -> (f64, f64) {
    let strength = s.strength;
    if s.method == Parallax::None
        || strength == 0.0
        || hmax.partial_cmp(&hmin) != Some(std::cmp::Ordering::Greater)
    {
        return p;
    }
    let vz = v[2].max(1e-3);
    let hmid = 0.5 * (hmin + hmax);
    match s.method {
        Parallax::None => p,
        Parallax::Offset => {
            let k = strength * (height(p.0, p.1) - hmid) / (vz + OFFSET_BIAS);
            (p.0 + k * v[0], p.1 + k * v[1])
        }
        Parallax::OffsetLimited => {
            let k = strength * (height(p.0, p.1) - hmid);
            (p.0 + k * v[0], p.1 + k * v[1])
        }
        Parallax::Steep | Parallax::Interpolated | Parallax::Relief => {
            let steps = s.steps.max(1);
            let depth_range = strength * (hmax - hmin);
            let dt = depth_range / steps as f64;
            let (sx, sr) = (-v[0] / vz, -v[1] / vz);
            let at = |t: f64| (p.0 + sx * t, p.1 + sr * t);
            // Signed gap: surface depth minus ray depth (> 0 while the ray is above the surface).
            let gap = |t: f64| {
                let q = at(t);
                strength * (hmax - height(q.0, q.1)) - t
            };
            let mut prev_t = 0.0;
            let mut prev_gap = gap(0.0);
            if prev_gap <= 0.0 {
                return p;
            }
            let mut t = 0.0;
            let mut g = prev_gap;
            for i in 1..=steps {
                t = dt * i as f64;
                g = gap(t);
                if g <= 0.0 {
                    break;
                }
                prev_t = t;
                prev_gap = g;
            }
            match s.method {
                Parallax::Steep => at(t),
                Parallax::Interpolated => {
                    let denom = prev_gap - g;
                    let w = if denom > 0.0 { prev_gap / denom } else { 1.0 };
                    at(prev_t + w * (t - prev_t))
                }
                _ => {
                    let (mut lo, mut hi) = (prev_t, t);
                    for _ in 0..s.search_steps {
                        let mid = 0.5 * (lo + hi);
                        if gap(mid) > 0.0 {
                            lo = mid;
                        } else {
                            hi = mid;
                        }
                    }
                    at(0.5 * (lo + hi))
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn settings(method: Parallax) -> ParallaxSettings {
        ParallaxSettings { method, steps: 64, search_steps: 16, strength: 1.0 }
    }

    #[test]
    fn straight_down_view_never_moves() {
        let h = |x: f64, r: f64| (x * 0.3).sin() + (r * 0.2).cos();
        for m in [
            Parallax::Offset,
            Parallax::OffsetLimited,
            Parallax::Steep,
            Parallax::Interpolated,
            Parallax::Relief,
        ] {
            let q = displace(h, -2.0, 2.0, (3.25, 7.5), [0.0, 0.0, 1.0], &settings(m));
            assert_eq!(q, (3.25, 7.5), "{m:?}");
        }
    }

    #[test]
    fn offset_formulas() {
        // Constant height 3 in [0, 4]: h − h_mid = 1.
        let h = |_: f64, _: f64| 3.0;
        let v = [0.6, 0.0, 0.8];
        let q = displace(h, 0.0, 4.0, (0.0, 0.0), v, &settings(Parallax::Offset));
        assert!((q.0 - 0.6 / (0.8 + 0.42)).abs() < 1e-12);
        let q = displace(h, 0.0, 4.0, (0.0, 0.0), v, &settings(Parallax::OffsetLimited));
        assert!((q.0 - 0.6).abs() < 1e-12);
    }

    #[test]
    fn steep_family_finds_a_flat_floor() {
        // A flat floor 2 texels below the top of the relief: the eye ray through p hits it at
        // depth 2, i.e. at p − 2·V.xy/V.z. Interpolated and relief find it exactly; steep to
        // within one layer.
        let h = |x: f64, _: f64| if x > 100.0 { 4.0 } else { 2.0 };
        let v = [0.6, 0.0, 0.8];
        let want = -2.0 * 0.6 / 0.8;
        for (m, tol) in [
            (Parallax::Steep, 4.0 / 64.0 * 0.75 + 1e-9),
            (Parallax::Interpolated, 1e-9),
            (Parallax::Relief, 1e-4),
        ] {
            let q = displace(h, 0.0, 4.0, (0.0, 0.0), v, &settings(m));
            assert!((q.0 - want).abs() <= tol, "{m:?}: {} vs {want}", q.0);
        }
    }
}
