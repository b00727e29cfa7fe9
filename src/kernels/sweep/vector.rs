//! The vector far field's driver and data layout: 16 lines of a family in lockstep
//! ([`far_field_fast`]), the map's major lines padded and chunked so a group's 17 heights per
//! column are one contiguous read ([`MajorLines`]), the per-thread scratch, and the layout of the
//! far field's sums ([`SumLayout`]). The intrinsics themselves are in `avx512`.

use super::*;

/// Where [`far_field_fast`] hands on a plane's rows (first texel, values) instead of filling a
/// plane in the image layout.
pub(super) type Emit<'e> = &'e mut dyn FnMut(usize, &[f32]);

/// Rows per band of a plane that [`far_field_fast`] hands on transposed (16 rows at 8192
/// columns: 512 KiB).
pub(super) const EMIT_ROWS: usize = 16;

/// Lanes of the vector far field: 16 lines of one family in lockstep.
pub(super) const FAR_LANES: usize = 16;
/// Margin of the padded major lines ([`MajorLines`]) on either side of the minor axis.
pub(super) const MINOR_PAD: usize = FAR_LANES + 2;

/// Minor texels per chunk of [`MajorLines`] (a power of two).
pub(super) const CHUNK: usize = 64;
/// A chunk's row: its CHUNK texels and the 16 after them, so a read of 17 starting in the chunk
/// stays in its row.
pub(super) const CHUNK_ROW: usize = CHUNK + FAR_LANES;

/// The map's major lines (image columns when the major axis is x, rows when it is y), each
/// padded by [`MINOR_PAD`] on both sides of the minor axis (the wrapped heights with `edge=wrap`, 0
/// with `edge=none`, where those lanes are masked), so 16 adjacent lines of a family read one
/// contiguous run of 17 heights per column with no wrapping or clamping.
///
/// Stored in chunks of [`CHUNK`] minor texels (padded positions), each chunk all major lines'
/// rows of [`CHUNK_ROW`] one after the other, so consecutive columns of a group of lines are 320
/// bytes apart rather than a whole line (8 KiB at 2048²): a sweep (or its copy, see
/// [`groups_avx512`]) reads a dozen columns per 4 KiB page, not a new page per column.
/// The chunked layout was chosen by measurement (docs/sweep.md, "Constants").
pub(super) struct MajorLines {
    /// Floats per chunk (major lines × CHUNK_ROW).
    pub(super) chunk: usize,
    pub(super) data: Vec<f32>,
}

impl MajorLines {
    pub(super) fn new(grid: &Grid<'_>, major_x: bool) -> MajorLines {
        let (w, h) = (grid.width, grid.height);
        let (wa, hb) = if major_x { (w, h) } else { (h, w) };
        let stride = hb + 2 * MINOR_PAD;
        let chunks = stride.div_ceil(CHUNK);
        let chunk = wa * CHUNK_ROW;
        let mut data = vec![0.0f32; chunks * chunk];
        let wrap = grid.edge == Edge::Wrap;
        data.par_chunks_mut(CHUNK_ROW).enumerate().for_each(|(i, row)| {
            let (ch, a) = (i / wa, i % wa);
            for (t, v) in row.iter_mut().enumerate() {
                let j = ch * CHUNK + t;
                if j >= stride {
                    break;
                }
                let b = j as i64 - MINOR_PAD as i64;
                let b = if wrap {
                    b.rem_euclid(hb as i64)
                } else if (0..hb as i64).contains(&b) {
                    b
                } else {
                    continue;
                } as usize;
                *v = if major_x { grid.heights[b * w + a] } else { grid.heights[a * w + b] };
            }
        });
        MajorLines { chunk, data }
    }

    /// Where minor `b` (−MINOR_PAD ≤ b < hb + MINOR_PAD − 16) of the major line whose row offset is
    /// `row` (major · CHUNK_ROW) lies in `data`.
    #[inline(always)]
    pub(super) fn at(chunk: usize, row: usize, b: i64) -> isize {
        let j = (b + MINOR_PAD as i64) as usize;
        ((j / CHUNK) * chunk + row + j % CHUNK) as isize
    }
}

/// Groups of lines whose tangents go into the sums together ([`add_batch_avx512`]); chosen by
/// measurement (docs/sweep.md, "Constants").
pub(super) const BATCH: usize = 8;

/// Groups of 16 lines swept side by side in one loop ([`groups_avx512`]); chosen by measurement
/// (docs/sweep.md, "Constants").
pub(super) const GROUPS: usize = 2;

/// Hull vertices a tangent walk compares per round ([`groups_avx512`]): the pairs of consecutive
/// vertices are compared independently, so the walk waits for one chain of compares per round
/// rather than per vertex; chosen by measurement (docs/sweep.md, "Constants").
pub(super) const WALK: usize = 4;

/// A unit of the in-memory build ([`Sweep::with_options`]): an azimuth's plane (and its
/// mirror's, when the two share their sweeps), or the near field's tables.
pub(super) enum Task<'p> {
    Far(usize, &'p mut [f32], Option<&'p mut [f32]>),
    NearTables,
}

/// A texel of a far-field plane one of whose two roles found nothing ahead: where its sum is
/// (`at`, in the sums' layout) and the weight of the role that may have found something
/// (`wt`), by which the sum is divided ([`finish_avx512`]). Only the texels within the near
/// field's reach of a line's end miss (about `NEAR_STEPS` · (W + H) an azimuth), so they are
/// listed rather than given a plane of weights, which cost 4 bytes a texel (268 MB at 8192²).
#[derive(Clone, Copy, Debug)]
pub(super) struct Miss {
    pub(super) at: usize,
    pub(super) wt: f32,
}

/// Per-thread scratch of [`far_field_fast`].
#[derive(Default)]
pub(super) struct Scratch {
    /// The texels (index into the sums) one of whose roles found nothing ahead, each with the
    /// other role's weight ([`Miss`]).
    pub(super) miss: Vec<Miss>,
    /// The scalar far field's weight sums ([`super::hull::far_field`]).
    pub(super) wsum: Vec<f32>,
    /// The hull stacks below their three registers, `st[depth·16 + lane]`: a vertex's column
    /// in the low 32 bits, the bits of its height in the high ones.
    pub(super) st: Vec<i64>,
    /// The tangents of a batch of groups, `sb[(slot·W + q)·16 + lane]` (−∞: none).
    pub(super) sb: Vec<f32>,
    /// The samples of the groups of one [`groups_avx512`] call, `ss[(u·G + g)·16 + lane]`,
    /// and their queries' heights, `sh[((q·2 + mirror)·G + g)·16 + lane]` (see there).
    pub(super) ss: Vec<f32>,
    pub(super) sh: Vec<f32>,
    /// Sums in major-line layout when that is not the image's, and per-azimuth tables.
    pub(super) acc: Vec<f32>,
    /// The mirror azimuth's `acc` and `miss`, and its query columns and sums' offsets.
    pub(super) acc2: Vec<f32>,
    pub(super) miss2: Vec<Miss>,
    pub(super) qs2: Vec<QCol>,
    pub(super) abase2: Vec<usize>,
    pub(super) fams: Vec<[(usize, i64, f64); 2]>,
    pub(super) abase: Vec<usize>,
    pub(super) cols: Vec<Col>,
    pub(super) qs: Vec<QCol>,
}

/// A column of one family: where lane 0's lower texel lies (minor, reduced modulo the map with
/// `edge=wrap`), the lerp weight, and where its major line lies in [`MajorLines`].
#[derive(Clone, Copy, Default)]
pub(super) struct Col {
    pub(super) start: i64,
    pub(super) wt: f32,
    /// The weight is exactly 0 (a line through the last texel is still on the surface).
    pub(super) wt0: bool,
    /// The major line's row in each chunk of [`MajorLines`] (major · [`CHUNK_ROW`]).
    pub(super) row: usize,
}

/// A query column of one family: whether the family holds one of the two sub-lines of the
/// column's texels, the shift from line to texel, and the weight.
#[derive(Clone, Copy, Default)]
pub(super) struct QCol {
    pub(super) on: bool,
    pub(super) shift: i64,
    pub(super) wt: f32,
    /// The other role's weight.
    pub(super) other: f32,
}

/// Everything a group of lines shares within one family and azimuth.
#[derive(Clone, Copy)]
pub(super) struct Family<'s> {
    pub(super) cols: &'s [Col],
    pub(super) qs: &'s [QCol],
    /// Offset of minor 0 of query column q in the sums' chunk 0 (major-line layout).
    pub(super) abase: &'s [usize],
    pub(super) lay: SumLayout,
    pub(super) data: &'s [f32],
    /// [`MajorLines::chunk`].
    pub(super) chunk: usize,
    pub(super) hb: i64,
    pub(super) wa: i64,
    pub(super) len: i64,
    pub(super) d: i64,
    pub(super) wrap: bool,
    /// Finite window: steps within R and the block length (see the module doc).
    pub(super) r_steps: Option<(i64, i64)>,
    pub(super) inv_step: f32,
    /// The curvature drop per major step², c' (0: none): samples are g = h − c'·u² at column
    /// u, a query at q starts from h0 − c'·q² and adds 2c'·q to its slope (module doc).
    pub(super) cc: f64,
    /// The mirror azimuth swept along ([`Lines::mirror`]): the column e of its query column 0
    /// (its query column u' sits at column e − u' of these lines), and its query columns.
    pub(super) mirror: Option<i64>,
    pub(super) mq: &'s [QCol],
    /// The column of query column 0 (0 unless paired with a mirror: [`mirror_end`]).
    pub(super) qoff: i64,
}

/// The far field of [`far_field`] in f32, 16 lines of a family at a time (AVX-512), the
/// curvature drop included: the same samples and hulls, so the same values up to f32 rounding
/// (tested against it). Each lane's hull is a stack, its top three vertices in registers (see
/// [`groups_avx512`]).
///
/// `mirror`: the opposite azimuth's lines as [`Lines::mirror`] of these, and its plane. Its
/// windows are these lines' windows seen from their other end: a window [s, s + R' − N] is
/// this azimuth's query at s − N looking right and the mirror's at s + R' looking left (with
/// a short window the two sets of windows overlap rather than coincide: [`mirror_end`]), so
/// one suffix pass and one prefix pass answer both, and the hull pushes (a large part of the
/// build) are shared by two azimuths. Only with a finite window (`edge=wrap`): the query
/// columns lie a multiple of the map's major size along the lines, on the same texels.
///
/// `fresh`: `out` was never touched (a plane of the far table, which is allocated zeroed and
/// so not yet mapped). The sums are then added up in the thread's scratch plane, already
/// mapped, and written to `out` once: adding into `out` itself would first map each of its
/// pages to the shared zero page (the add reads) and then copy it on the write, which costs a
/// TLB shootdown across the pool's threads per 4 KiB page.
#[allow(clippy::too_many_arguments)] // the planes, their scratch and how they are handed on
pub(super) fn far_field_fast(
    grid: &Grid<'_>,
    ml: &MajorLines,
    lines: Lines,
    reach: Option<f64>,
    curv: f64,
    out: &mut [f32],
    sc: &mut Scratch,
    mut emit: Option<Emit<'_>>,
    fresh: bool,
    mut mirror: Option<(Lines, &mut [f32])>,
) {
    let (w, h) = (grid.width, grid.height);
    let (wa, hb) = if lines.major_x { (w, h) } else { (h, w) };
    let r_steps = reach.map(|r| (r / lines.step + 1e-9).floor() as i64);
    let d = NEAR_STEPS as i64;
    if r_steps.is_some_and(|r| r < d) {
        if let Some(emit) = emit.as_deref_mut() {
            let zeros = vec![0.0f32; w * EMIT_ROWS.min(h)];
            for y0 in (0..h).step_by(EMIT_ROWS) {
                emit(y0 * w, &zeros[..EMIT_ROWS.min(h - y0) * w]);
            }
        }
        return;
    }
    let wrap = grid.edge == Edge::Wrap;
    // The mirror needs a window and lines that wrap; its query column 0 sits at column e.
    let e = match (&mirror, r_steps) {
        (Some((m, _)), Some(_)) if wrap => Some(m.at.0),
        _ => None,
    };
    debug_assert!(e.is_some() == mirror.is_some() && (e.is_none() || emit.is_none()));
    // Paired, the sweeps run over the lines' own columns (the mirror's are columns of these
    // lines too), this azimuth's texel u on column `qoff` + u; alone, over its look order.
    let (base, qoff) = match e {
        Some(_) => (Lines { at: (0, 1), ..lines }, lines.at.0),
        None => (lines, 0),
    };
    let len = match (wrap, r_steps) {
        (true, Some(r)) => (qoff + wa as i64 + r).max(e.map_or(0, |e| e - d + 1)),
        _ => wa as i64,
    };
    // The columns whose heights a query reads reach the mirror's last query column.
    let ncols = len.max(e.map_or(0, |e| e + 1));
    let hbi = hb as i64;
    let major = |u: i64| -> usize {
        let u = if wrap { u.rem_euclid(wa as i64) } else { u };
        (if lines.sign > 0 { u } else { wa as i64 - 1 - u }) as usize
    };
    // Sums are kept in major-line layout (`major · hb + minor`), so the 16 texels of a query
    // are contiguous; that is the image layout when the major axis is y.
    let mut fams = std::mem::take(&mut sc.fams);
    fams.clear();
    fams.extend((0..wa as i64).map(|u| lines.pair(u)));
    let (sh_lo, sh_hi) = fams
        .iter()
        .flatten()
        .fold((i64::MAX, i64::MIN), |(lo, hi), &(_, s, _)| (lo.min(s), hi.max(s)));
    let via_acc = lines.major_x || fresh;
    // Sums in the scratch planes are kept in chunks of SUM_CHUNK minor texels (see `SumLayout`); in
    // `out` itself (the spill's planes along y), in its own layout.
    let lay = SumLayout { chunk: if via_acc { wa * SUM_CHUNK } else { 0 } };
    let plane = if via_acc { hb.div_ceil(SUM_CHUNK) * SUM_CHUNK * wa } else { w * h };
    let planes = if e.is_some() { 2 } else { 1 };
    let mut acc = std::mem::take(&mut sc.acc);
    let mut acc2 = std::mem::take(&mut sc.acc2);
    // The scratch planes are all zeros between calls (`finish_avx512` clears what it reads),
    // so they are only resized (a separate clear was a pass over 64 MiB per pair at 2048²).
    for (p, (a, miss)) in
        [(&mut acc, &mut sc.miss), (&mut acc2, &mut sc.miss2)].into_iter().enumerate()
    {
        miss.clear();
        if p < planes && via_acc {
            a.resize(plane, 0.0);
        }
    }
    sc.st.resize(GROUPS * len as usize * FAR_LANES, 0);
    sc.sb.resize(planes * (BATCH + GROUPS) * wa * FAR_LANES, f32::NEG_INFINITY);
    let mut abase = std::mem::take(&mut sc.abase);
    abase.clear();
    abase.extend((0..wa as i64).map(|u| major(u) * lay.row(hb)));
    let mut abase2 = std::mem::take(&mut sc.abase2);
    let mut fams2: Vec<[(usize, i64, f64); 2]> = Vec::new();
    abase2.clear();
    if let Some((ml2, _)) = &mirror {
        // The mirror's own look order, as `major` for it (its query columns are on the map).
        let m2 = |u: i64| (if ml2.sign > 0 { u } else { wa as i64 - 1 - u }) as usize;
        abase2.extend((0..wa as i64).map(|u| m2(u) * lay.row(hb)));
        fams2.extend((0..wa as i64).map(|u| ml2.pair(u)));
    }
    let mut cols = std::mem::take(&mut sc.cols);
    let mut qs = std::mem::take(&mut sc.qs);
    let mut qs2 = std::mem::take(&mut sc.qs2);
    let (sums, sums2): (&mut [f32], &mut [f32]) = match (via_acc, mirror.as_mut()) {
        (true, _) => (&mut acc, &mut acc2),
        (false, Some((_, o2))) => (out, o2),
        (false, None) => (out, &mut acc2),
    };
    let q_col = |p: &[(usize, i64, f64); 2], k: usize| {
        let role = |r: usize| QCol {
            on: true,
            shift: if wrap { p[r].1.rem_euclid(hbi) } else { p[r].1 },
            wt: p[r].2 as f32,
            other: p[1 - r].2 as f32,
        };
        (0..2).find(|&r| p[r].0 == k).map_or(QCol::default(), role)
    };
    for k in 0..SUB {
        cols.clear();
        cols.extend((0..ncols).map(|u| {
            let (off, wt) = base.sample(k, u);
            let start = if wrap { off.rem_euclid(hbi) } else { off };
            Col { start, wt: wt as f32, wt0: wt == 0.0, row: major(u) * CHUNK_ROW }
        }));
        qs.clear();
        qs.extend(fams.iter().map(|p| q_col(p, k)));
        qs2.clear();
        qs2.extend(fams2.iter().map(|p| q_col(p, k)));
        let fam = Family {
            cols: &cols,
            qs: &qs,
            abase: &abase,
            lay,
            data: &ml.data,
            chunk: ml.chunk,
            hb: hbi,
            wa: wa as i64,
            len,
            d,
            wrap,
            r_steps: r_steps.map(|r| (r, r - d + 1)),
            inv_step: (1.0 / lines.step) as f32,
            cc: curv * lines.step * lines.step,
            mirror: e,
            mq: &qs2,
            qoff,
        };
        // The mirror's sums are added as this family's with its query columns.
        let fam2 = Family { qs: &qs2, abase: &abase2, ..fam };
        let (i_lo, i_hi) = if wrap { (0, hbi - 1) } else { (sh_lo, hbi - 1 + sh_hi) };
        let mut i0 = i_lo;
        let mut batch = [(0i64, 0u32); BATCH + GROUPS];
        let mut nb = 0;
        while i0 <= i_hi {
            // Up to GROUPS groups of 16 lines side by side (a missing one has no lines).
            let mut gs = [(0i64, 0u32); GROUPS];
            let mut ng = 0;
            while ng < GROUPS && i0 <= i_hi {
                let nl = (i_hi - i0 + 1).min(FAR_LANES as i64) as u32;
                gs[ng] = (i0, nl);
                batch[nb + ng] = (i0, nl);
                ng += 1;
                i0 += FAR_LANES as i64;
            }
            #[cfg(target_arch = "x86_64")]
            // SAFETY: only called when the CPU has AVX-512F (see `Sweep::with_options`).
            unsafe {
                groups_avx512::<GROUPS>(&fam, gs, nb, sc)
            };
            nb += ng;
            if nb >= BATCH || i0 > i_hi {
                #[cfg(target_arch = "x86_64")]
                // SAFETY: as above.
                unsafe {
                    add_batch_avx512(&fam, &batch[..nb], 0, sums, &sc.sb, &mut sc.miss);
                    if e.is_some() {
                        let s0 = BATCH + GROUPS;
                        add_batch_avx512(&fam2, &batch[..nb], s0, sums2, &sc.sb, &mut sc.miss2);
                    }
                };
                nb = 0;
            }
        }
    }
    #[cfg(target_arch = "x86_64")]
    // SAFETY: only called when the CPU has AVX-512F (see `Sweep::with_options`).
    unsafe {
        finish_avx512(lines.major_x, via_acc, lay, emit, &mut acc, &mut sc.miss, out, w, h);
        if let Some((ml2, out2)) = mirror.as_mut().filter(|_| e.is_some()) {
            finish_avx512(ml2.major_x, via_acc, lay, None, &mut acc2, &mut sc.miss2, out2, w, h);
        }
    }
    sc.fams = fams;
    sc.acc = acc;
    sc.acc2 = acc2;
    sc.abase = abase;
    sc.abase2 = abase2;
    sc.cols = cols;
    sc.qs = qs;
    sc.qs2 = qs2;
}

/// Minor texels per chunk of the far field's sums (see [`SumLayout`]).
pub(super) const SUM_CHUNK: usize = 128;

/// Where the sums of a far-field plane are kept: with `chunk` = 0 in major-line layout
/// (`major · hb + minor`), else in chunks of [`SUM_CHUNK`] minor texels, each chunk (`chunk` floats)
/// every major line's run of SUM_CHUNK in turn (`(minor / SUM_CHUNK) · chunk + major · SUM_CHUNK + minor % SUM_CHUNK`).
/// The tangents of a batch of 8 groups of lines go into 128 adjacent texels of one query
/// column after another, so in major-line layout every column's run was a new row, a new page
/// (8 KiB rows at 2048²), and the adds waited on those misses even prefetched (more than half
/// of [`add_batch_avx512`]'s profile); in chunks, a page holds 8 columns' runs.
#[derive(Clone, Copy)]
pub(super) struct SumLayout {
    pub(super) chunk: usize,
}

impl SumLayout {
    /// The floats a major line's run takes within a chunk (the whole minor size `hb` when
    /// not chunked).
    #[inline(always)]
    pub(super) fn row(self, hb: usize) -> usize {
        if self.chunk == 0 {
            hb
        } else {
            SUM_CHUNK
        }
    }

    /// The offset of minor `b` of the line whose run starts at `base` (major · [`Self::row`]).
    #[inline(always)]
    pub(super) fn at(self, base: usize, b: usize) -> usize {
        if self.chunk == 0 {
            base + b
        } else {
            (b / SUM_CHUNK) * self.chunk + base + b % SUM_CHUNK
        }
    }
}

/// For the group of `nl` lines from `i0` at a query column whose lines lie `shift` from its
/// texels: the lanes whose texel is in the map, and lane 0's minor (reduced modulo the map
/// with `edge=wrap`, where every lane's texel is).
#[inline]
pub(super) fn texels_at(f: &Family<'_>, i0: i64, nl: u32, shift: i64) -> (u16, i64) {
    let b0 = i0 - shift;
    if f.wrap {
        let all = if nl >= 16 { 0xffff } else { ((1u32 << nl) - 1) as u16 };
        (all, b0.rem_euclid(f.hb))
    } else {
        (lane_range(b0, f.hb, nl), b0)
    }
}

/// The lanes (bit l: lane l) whose minor b0 + l lies in 0..lim, of the first `nl`.
#[inline]
pub(super) fn lane_range(b0: i64, lim: i64, nl: u32) -> u16 {
    let lo = (-b0).clamp(0, 16) as u32;
    let hi = (lim - b0).clamp(0, nl as i64) as u32;
    if hi <= lo {
        return 0;
    }
    let upto = |n: u32| if n >= 16 { 0xffffu16 } else { ((1u32 << n) - 1) as u16 };
    upto(hi) & !upto(lo)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The vector far field against the scalar f64 one of the same samples (its oracle): random
    /// maps, both edges, odd sizes, thin strips and 1×1, finite R and unlimited, every azimuth
    /// of 32 (both major axes, both signs, slopes of both signs).
    #[test]
    fn the_vector_far_field_matches_the_scalar_one() {
        if !Isa::Avx512.supported() {
            eprintln!("no AVX-512: the vector far field is not used on this CPU");
            return;
        }
        let mut seed = 777u64;
        let mut rnd = || {
            seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (seed >> 40) as f32 / (1u64 << 24) as f32
        };
        // 150 and 133 lines: more groups than a batch, and an odd count of them, so the last
        // call has a group of no lines beside a real one.
        let sizes = [
            (1usize, 1usize),
            (1, 37),
            (37, 1),
            (2, 3),
            (3, 40),
            (45, 38),
            (70, 17),
            (150, 5),
            (6, 133),
        ];
        let (mut paired, mut shifted) = (0, 0);
        for (w, h) in sizes {
            for rough in [2.0f32, 12.0] {
                let heights: Vec<f32> = (0..w * h).map(|_| rnd() * rough).collect();
                for edge in [Edge::None, Edge::Wrap] {
                    let g = Grid::new(w, h, &heights, edge, crate::params::YAxis::Up);
                    let mls = [MajorLines::new(&g, false), MajorLines::new(&g, true)];
                    for radius in [Some(17.0), Some(30.0), Some(61.5), None] {
                        let reach = match (radius, edge) {
                            (Some(r), _) => Some(r),
                            (None, Edge::Wrap) => Some(w.max(h) as f64),
                            (None, Edge::None) => None,
                        };
                        let mut sc = Scratch::default();
                        // Without the curvature drop, and with one that lowers the far end of
                        // the longest line by several times the relief.
                        for (n, curv) in (0..32).flat_map(|n| [(n, 0.0), (n, 2e-3)]) {
                            let d = exact::direction(n as f64 * 2.0 * PI / 32.0, g.row_step());
                            let lines = Lines::new(d);
                            let mut want = vec![0.0f32; w * h];
                            let mut wsum = Vec::new();
                            far_field(&g, lines, reach, curv, &mut want, &mut wsum);
                            let ml = &mls[usize::from(lines.major_x)];
                            let close = |got: &[f32], want: &[f32], what: &str| {
                                for (t, (a, b)) in got.iter().zip(want).enumerate() {
                                    assert!(
                                        (a - b).abs() <= 2e-5 * (1.0 + b.abs()),
                                        "{w}×{h} {edge:?} R {radius:?} bin {n} curvature \
                                         {curv} texel {t} {what}: {a} vs {b}"
                                    );
                                }
                            };
                            for fresh in [false, true] {
                                let mut got = vec![0.0f32; w * h];
                                far_field_fast(
                                    &g, ml, lines, reach, curv, &mut got, &mut sc, None, fresh,
                                    None,
                                );
                                close(&got, &want, &format!("fresh {fresh}"));
                            }
                            // Swept with the opposite azimuth where the bake pairs them: both
                            // planes against the scalar sweeps of each alone.
                            let Some((a, e)) = mirror_end(&g, lines, reach) else { continue };
                            paired += 1;
                            shifted += usize::from(a > 0);
                            // Its texels where the pairing puts them, and the mirror.
                            let lines = Lines { at: (a, 1), ..lines };
                            let mut want = vec![0.0f32; w * h];
                            far_field(&g, lines, reach, curv, &mut want, &mut wsum);
                            let mirror = lines.mirror(e);
                            let mut want2 = vec![0.0f32; w * h];
                            far_field(&g, mirror, reach, curv, &mut want2, &mut wsum);
                            for fresh in [false, true] {
                                let (mut got, mut got2) = (vec![0.0f32; w * h], vec![0.0; w * h]);
                                far_field_fast(
                                    &g,
                                    ml,
                                    lines,
                                    reach,
                                    curv,
                                    &mut got,
                                    &mut sc,
                                    None,
                                    fresh,
                                    Some((mirror, &mut got2)),
                                );
                                close(&got, &want, &format!("paired, fresh {fresh}"));
                                close(&got2, &want2, &format!("its mirror, fresh {fresh}"));
                            }
                        }
                    }
                }
            }
        }
        // Every wrapped size pairs at `unlimited`, and some at finite radii with the texels
        // a whole map further along the lines (a short window: `mirror_end`).
        assert!(paired >= 9 * 2 * 2 * 32, "only {paired} paired sweeps");
        assert!(shifted > 0, "no pairing of a short window");
    }
}
