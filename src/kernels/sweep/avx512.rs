//! The AVX-512 intrinsics of the vector far field: 16 hulls in lockstep with their three nearest
//! vertices in registers and the rest stacked by depth in memory ([`stash`], [`unstash`]),
//! the tangent walks, the transposes, and the sums of a batch of groups.

use super::*;

/// The sums of a far-field plane (`acc` if `via_acc`, else already in `out`; see
/// [`SumLayout`]) divided by their weights where a role missed (`miss`, emptied), into `out`
/// in the image layout, or band by band to `emit` (the sweeps along x only); `acc` is left
/// all zeros for the next plane. Along x, the sums are transposed 16×16 texels at a time
/// in registers (the scalar transpose was 4–5 % of a bake's profile).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
#[allow(clippy::too_many_arguments)] // the plane's layouts and where it goes
pub(super) unsafe fn finish_avx512(
    major_x: bool,
    via_acc: bool,
    lay: SumLayout,
    emit: Option<Emit<'_>>,
    acc: &mut [f32],
    miss: &mut Vec<Miss>,
    out: &mut [f32],
    w: usize,
    h: usize,
) {
    use std::arch::x86_64::*;
    // Helpers, not closures: a closure is compiled without the function's target features.
    let mask = |n: usize| if n >= 16 { 0xffff } else { ((1u32 << n) - 1) as u16 };
    apply_misses(miss, if via_acc { &mut *acc } else { &mut *out });
    if let (true, Some(emit)) = (major_x, emit) {
        // Transposed and normalised a band of rows at a time, each band handed on: no plane
        // in the image layout is ever whole. A band's rows lie in one chunk of the sums.
        let mut buf = vec![0.0f32; w * EMIT_ROWS.min(h)];
        for y0 in (0..h).step_by(EMIT_ROWS) {
            let ny = EMIT_ROWS.min(h - y0);
            for x0 in (0..w).step_by(16) {
                let nx = 16.min(w - x0);
                let t = take_block(lay, acc, x0, y0, nx, ny, h);
                for (j, &v) in t.iter().enumerate().take(ny) {
                    _mm512_mask_storeu_ps(buf.as_mut_ptr().add(j * w + x0), mask(nx), v);
                }
            }
            emit(y0 * w, &buf[..ny * w]);
        }
    } else if major_x {
        let op = out.as_mut_ptr();
        for x0 in (0..w).step_by(16) {
            let nx = 16.min(w - x0);
            for y0 in (0..h).step_by(16) {
                let ny = 16.min(h - y0);
                let t = take_block(lay, acc, x0, y0, nx, ny, h);
                for (j, &v) in t.iter().enumerate().take(ny) {
                    _mm512_mask_storeu_ps(op.add((y0 + j) * w + x0), mask(nx), v);
                }
            }
        }
    } else if via_acc {
        // Rows of the image are rows of the sums, a chunk's run at a time.
        for y in 0..h {
            for x0 in (0..w).step_by(16) {
                let n = 16.min(w - x0);
                let v = take16(acc, lay.at(y * lay.row(w), x0), n);
                _mm512_mask_storeu_ps(out.as_mut_ptr().add(y * w + x0), mask(n), v);
            }
        }
    }
}

/// Divides each missed texel's sum by the weight of its roles that may have found something
/// (its entries' `wt` added, 0 first: at most two a texel, so in any order the same bits), where
/// that weight is above 0, and empties the list.
fn apply_misses(miss: &mut Vec<Miss>, sums: &mut [f32]) {
    miss.sort_unstable_by_key(|m| m.at);
    let mut k = 0;
    while k < miss.len() {
        let at = miss[k].at;
        let mut ws = 0.0f32;
        while k < miss.len() && miss[k].at == at {
            ws += miss[k].wt;
            k += 1;
        }
        if ws > 0.0 {
            sums[at] /= ws;
        }
    }
    miss.clear();
}

/// The normalised sums of 16 texels at `o` (the first `n`; the rest 0), cleared.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
#[inline]
pub(super) unsafe fn take16(acc: &mut [f32], o: usize, n: usize) -> std::arch::x86_64::__m512 {
    use std::arch::x86_64::*;
    let m = if n >= 16 { 0xffff } else { ((1u32 << n) - 1) as u16 };
    let pa = acc.as_mut_ptr().add(o);
    let a = _mm512_maskz_loadu_ps(m, pa);
    _mm512_mask_storeu_ps(pa, m, _mm512_setzero_ps());
    a
}

/// Along x: the normalised sums of columns x0 .. x0 + `nx` and rows y0 .. y0 + `ny` (minor
/// size `h`), cleared, transposed: element j of the result is row y0 + j.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
#[inline]
#[allow(clippy::too_many_arguments)] // the block and its layout
pub(super) unsafe fn take_block(
    lay: SumLayout,
    acc: &mut [f32],
    x0: usize,
    y0: usize,
    nx: usize,
    ny: usize,
    h: usize,
) -> [std::arch::x86_64::__m512; 16] {
    use std::arch::x86_64::*;
    let mut r = [_mm512_setzero_ps(); 16];
    for (i, v) in r.iter_mut().enumerate().take(nx) {
        *v = take16(acc, lay.at((x0 + i) * lay.row(h), y0), ny);
    }
    transpose16(r)
}

/// The 16×16 transpose of `r` (row i: r[i]) in registers: 64 shuffles.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
#[inline]
pub(super) unsafe fn transpose16(
    r: [std::arch::x86_64::__m512; 16],
) -> [std::arch::x86_64::__m512; 16] {
    use std::arch::x86_64::*;
    let mut t = [_mm512_setzero_ps(); 16];
    for k in 0..8 {
        t[2 * k] = _mm512_unpacklo_ps(r[2 * k], r[2 * k + 1]);
        t[2 * k + 1] = _mm512_unpackhi_ps(r[2 * k], r[2 * k + 1]);
    }
    // Within each 128-bit lane l of u[4j + c]: column 4l + c of rows 4j .. 4j + 4.
    let mut u = [_mm512_setzero_ps(); 16];
    for j in 0..4 {
        let (a, b) = (_mm512_castps_pd(t[4 * j]), _mm512_castps_pd(t[4 * j + 1]));
        let (c, d) = (_mm512_castps_pd(t[4 * j + 2]), _mm512_castps_pd(t[4 * j + 3]));
        u[4 * j] = _mm512_castpd_ps(_mm512_unpacklo_pd(a, c));
        u[4 * j + 1] = _mm512_castpd_ps(_mm512_unpackhi_pd(a, c));
        u[4 * j + 2] = _mm512_castpd_ps(_mm512_unpacklo_pd(b, d));
        u[4 * j + 3] = _mm512_castpd_ps(_mm512_unpackhi_pd(b, d));
    }
    let mut o = [_mm512_setzero_ps(); 16];
    for c in 0..4 {
        let v0 = _mm512_shuffle_f32x4::<0x88>(u[c], u[4 + c]);
        let w0 = _mm512_shuffle_f32x4::<0xdd>(u[c], u[4 + c]);
        let v1 = _mm512_shuffle_f32x4::<0x88>(u[8 + c], u[12 + c]);
        let w1 = _mm512_shuffle_f32x4::<0xdd>(u[8 + c], u[12 + c]);
        o[c] = _mm512_shuffle_f32x4::<0x88>(v0, v1);
        o[4 + c] = _mm512_shuffle_f32x4::<0x88>(w0, w1);
        o[8 + c] = _mm512_shuffle_f32x4::<0xdd>(v0, v1);
        o[12 + c] = _mm512_shuffle_f32x4::<0xdd>(w0, w1);
    }
    o
}

/// The lanes of `m` of (t, y) into the packed stack `st` at the entries `i` (see
/// [`Scratch::st`]): two scatters of 8 entries, not two of 16 (a gather or scatter costs by
/// the entry here).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
#[inline]
pub(super) unsafe fn stash(
    st: *mut i64,
    m: u16,
    i: std::arch::x86_64::__m512i,
    t: std::arch::x86_64::__m512i,
    y: std::arch::x86_64::__m512,
) {
    use std::arch::x86_64::*;
    let y = _mm512_castps_si512(y);
    let lo = _mm512_permutex2var_epi32(
        t,
        _mm512_setr_epi32(0, 16, 1, 17, 2, 18, 3, 19, 4, 20, 5, 21, 6, 22, 7, 23),
        y,
    );
    let hi = _mm512_permutex2var_epi32(
        t,
        _mm512_setr_epi32(8, 24, 9, 25, 10, 26, 11, 27, 12, 28, 13, 29, 14, 30, 15, 31),
        y,
    );
    _mm512_mask_i32scatter_epi64::<8>(st, m as u8, _mm512_castsi512_si256(i), lo);
    _mm512_mask_i32scatter_epi64::<8>(st, (m >> 8) as u8, _mm512_extracti64x4_epi64::<1>(i), hi);
}

/// The entries `i` of the packed stack `st` into the lanes of `m` of (t, y).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
#[inline]
pub(super) unsafe fn unstash(
    st: *const i64,
    m: u16,
    i: std::arch::x86_64::__m512i,
    t: std::arch::x86_64::__m512i,
    y: std::arch::x86_64::__m512,
) -> (std::arch::x86_64::__m512i, std::arch::x86_64::__m512) {
    use std::arch::x86_64::*;
    let z = _mm512_setzero_si512();
    let lo = _mm512_mask_i32gather_epi64::<8>(z, m as u8, _mm512_castsi512_si256(i), st);
    let hi =
        _mm512_mask_i32gather_epi64::<8>(z, (m >> 8) as u8, _mm512_extracti64x4_epi64::<1>(i), st);
    unpack(m, lo, hi, t, y)
}

/// Lanes 0–7 (`lo`) and 8–15 (`hi`) of packed entries into the lanes of `m` of (t, y).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
#[inline]
pub(super) unsafe fn unpack(
    m: u16,
    lo: std::arch::x86_64::__m512i,
    hi: std::arch::x86_64::__m512i,
    t: std::arch::x86_64::__m512i,
    y: std::arch::x86_64::__m512,
) -> (std::arch::x86_64::__m512i, std::arch::x86_64::__m512) {
    use std::arch::x86_64::*;
    let even = _mm512_setr_epi32(0, 2, 4, 6, 8, 10, 12, 14, 16, 18, 20, 22, 24, 26, 28, 30);
    let odd = _mm512_setr_epi32(1, 3, 5, 7, 9, 11, 13, 15, 17, 19, 21, 23, 25, 27, 29, 31);
    let nt = _mm512_permutex2var_epi32(lo, even, hi);
    let ny = _mm512_castsi512_ps(_mm512_permutex2var_epi32(lo, odd, hi));
    (_mm512_mask_mov_epi32(t, m, nt), _mm512_mask_mov_ps(y, m, ny))
}

/// `G` groups of up to 16 lines of a family (group g: lines `gs[g].0 ..` `+ gs[g].1`, its
/// tangents into batch slot `slot0 + g`; a group of 0 lines does nothing), swept in lockstep:
/// the suffix (or whole-line) pass right to left, then with a finite window the prefix pass
/// left to right, the weighted tangents into the slots (and the texels whose role found
/// nothing listed in `sc.miss`) by [`add_batch_avx512`].
///
/// Each lane's hull is a stack: the three vertices nearest the sweep's position in registers
/// (t1, t2, t3: column and height), the rest in memory by depth ([`Scratch::st`], a region
/// per group), a few KiB that stay in L1. A push spills t3 (one masked scatter), a pop
/// refills it (one masked gather, needed only a pop later), so short pops and query walks
/// wait for nothing; the prefix pass's queries walk the stack from its bottom with plain
/// loads.
///
/// Why several groups at once: a group's pops and tangent walks are one chain of dependent
/// compares, gathers and data-dependent branches, so one group alone leaves the core waiting
/// on latency. The groups of a call share every column (the same family), so their chains
/// run side by side in one loop, and each loop exit (a branch that mispredicts) is paid once
/// for all of them (measured: [`GROUPS`]).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
pub(super) unsafe fn groups_avx512<const G: usize>(
    f: &Family<'_>,
    gs: [(i64, u32); G],
    slot0: usize,
    sc: &mut Scratch,
) {
    use std::arch::x86_64::*;
    let wa = f.wa as usize;
    let lane = _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
    let none = _mm512_set1_epi32(-1);
    let zero_i = _mm512_setzero_si512();
    let one_i = _mm512_set1_epi32(1);
    let ninf = _mm512_set1_ps(f32::NEG_INFINITY);
    let data = f.data.as_ptr();
    let region = f.len as usize * FAR_LANES;
    let (i0, nl) = (gs.map(|g| g.0), gs.map(|g| g.1));
    let all = nl.map(|n| if n >= 16 { 0xffff } else { ((1u32 << n) - 1) as u16 });
    let mut sb = [std::ptr::null_mut::<f32>(); G];
    let mut sbm = [std::ptr::null_mut::<f32>(); G];
    let mut st = [std::ptr::null_mut::<i64>(); G];
    // Samples and queries' heights copied first where the passes are two (see below).
    let copied = f.r_steps.is_some();
    if copied {
        sc.ss.resize(f.len.max(0) as usize * G * FAR_LANES, 0.0);
        sc.sh.resize(wa * 2 * G * FAR_LANES, 0.0);
    }
    let (ss, sh) = (sc.ss.as_mut_ptr(), sc.sh.as_mut_ptr());
    for g in 0..G {
        // This group's tangents: its slot of the batch; the query columns the suffix pass does
        // not reach (within N of the line's end) have none.
        let slot = &mut sc.sb[(slot0 + g) * wa * FAR_LANES..][..wa * FAR_LANES];
        slot[(f.len - f.d - f.qoff).clamp(0, f.wa) as usize * FAR_LANES..].fill(f32::NEG_INFINITY);
        sb[g] = slot.as_mut_ptr();
        st[g] = sc.st.as_mut_ptr().add(g * region);
        if f.mirror.is_some() {
            // The mirror's tangents: the same slot in the second half of the batch's slots.
            sbm[g] = sc.sb[(BATCH + GROUPS + slot0 + g) * wa * FAR_LANES..][..wa * FAR_LANES]
                .as_mut_ptr();
        }
    }
    // The hulls' registers and memory depths, per group.
    let (mut t1, mut t2, mut t3, mut dep) = ([none; G], [none; G], [none; G], [zero_i; G]);
    let (mut y1, mut y2, mut y3) = ([ninf; G], [ninf; G], [ninf; G]);
    // The highest sample since the last reset, per group (read by the prefix pass only).
    let mut hmax = [ninf; G];
    macro_rules! reset {
        () => {{
            (t1, t2, t3, dep) = ([none; G], [none; G], [none; G], [zero_i; G]);
            (y1, y2, y3) = ([ninf; G], [ninf; G], [ninf; G]);
            hmax = [ninf; G];
        }};
    }
    macro_rules! idx {
        ($t:expr) => {
            _mm512_add_epi32(_mm512_slli_epi32::<4>($t), lane)
        };
    }
    macro_rules! load_h0 {
        ($q:expr, $b0:expr) => {
            _mm512_loadu_ps(data.offset(MajorLines::at(f.chunk, f.cols[$q as usize].row, $b0)))
        };
    }
    // A query at column q (query column `qc`; from the right if `$mir`): its abscissa, the
    // slope's curvature term, and per group the lanes whose texel is on the map and whose hull
    // is not empty, with their heights on the hulls of g (module doc).
    macro_rules! query_at {
        ($q:expr, $qc:expr, $mir:expr, $k:expr) => {{
            let q = $q;
            let shift = $qc.shift;
            let q_drop = _mm512_set1_ps((f.cc * (q * q) as f64) as f32);
            let (mut qm, mut hq) = ([0u16; G], [ninf; G]);
            let row = sh.wrapping_add((($k as usize) * 2 + usize::from($mir)) * G * FAR_LANES);
            for g in 0..G {
                let (tm, b0) = texels_at(f, i0[g], nl[g], shift);
                qm[g] = tm & _mm512_cmpge_epi32_mask(t1[g], zero_i);
                if qm[g] != 0 {
                    let h = if copied {
                        _mm512_loadu_ps(row.add(g * FAR_LANES))
                    } else {
                        load_h0!(q, b0)
                    };
                    hq[g] = _mm512_sub_ps(h, q_drop);
                }
            }
            let corr = 2.0 * f.cc * q as f64;
            let corr = if $mir { -corr } else { corr };
            (_mm512_set1_ps(q as f32), _mm512_set1_ps(corr as f32), qm, hq)
        }};
    }
    // Lanes of group g whose sample at column c (column u) is on the surface, and their
    // samples (copied beforehand with two passes, see below; else read here).
    macro_rules! lanes_at {
        ($c:expr, $g:expr) => {{
            let (c, g) = ($c, $g);
            let s = c.start + i0[g];
            if f.wrap {
                all[g]
            } else {
                lane_range(s, f.hb - 1 + i64::from(c.wt0), nl[g])
            }
        }};
    }
    // The sample of group g at column c, from the major lines.
    macro_rules! lerp_at {
        ($c:expr, $g:expr) => {{
            let (c, g) = ($c, $g);
            let mut s = c.start + i0[g];
            if f.wrap && s >= f.hb {
                s -= f.hb;
            }
            let p = data.offset(MajorLines::at(f.chunk, c.row, s));
            let a = _mm512_loadu_ps(p);
            let b = _mm512_loadu_ps(p.add(1));
            _mm512_add_ps(a, _mm512_mul_ps(_mm512_sub_ps(b, a), _mm512_set1_ps(c.wt)))
        }};
    }
    // Prefetches the heights of column u's samples.
    macro_rules! prefetch {
        ($u:expr) => {{
            let u = $u;
            if (0..f.len).contains(&u) {
                let c = f.cols[u as usize];
                for g in 0..G {
                    let s = (c.start + i0[g]).clamp(-(MINOR_PAD as i64), f.hb + 1);
                    let s = if f.wrap && s >= f.hb { s - f.hb } else { s };
                    let p = data.wrapping_offset(MajorLines::at(f.chunk, c.row, s));
                    _mm_prefetch::<_MM_HINT_T0>(p as *const i8);
                    _mm_prefetch::<_MM_HINT_T0>(p.wrapping_add(16) as *const i8);
                }
            }
        }};
    }
    macro_rules! sample {
        ($c:expr, $g:expr, $u:expr) => {{
            let (c, g, u) = ($c, $g, $u as usize);
            let vm = lanes_at!(c, g);
            let v = if vm == 0 {
                ninf
            } else if copied {
                _mm512_loadu_ps(ss.add((u * G + g) * FAR_LANES))
            } else {
                lerp_at!(c, g)
            };
            (vm, v)
        }};
    }
    // Pops the lanes of `pm` of group g: t1 ← t2 ← t3, which leaves a hole in t3 (−1 with
    // vertices left in memory); only a lane that had a hole already refills t2 from memory (a
    // gather). So a pop after a push, or a push after a pop, moves nothing between registers
    // and memory.
    macro_rules! pop {
        ($g:expr, $pm:expr) => {{
            let (g, pm) = ($g, $pm);
            let gm = pm
                & _mm512_cmplt_epi32_mask(t3[g], zero_i)
                & _mm512_cmpgt_epi32_mask(dep[g], zero_i);
            t1[g] = _mm512_mask_mov_epi32(t1[g], pm, t2[g]);
            y1[g] = _mm512_mask_mov_ps(y1[g], pm, y2[g]);
            t2[g] = _mm512_mask_mov_epi32(t2[g], pm, t3[g]);
            y2[g] = _mm512_mask_mov_ps(y2[g], pm, y3[g]);
            t3[g] = _mm512_mask_mov_epi32(t3[g], pm, none);
            if gm != 0 {
                dep[g] = _mm512_mask_sub_epi32(dep[g], gm, dep[g], one_i);
                let i = idx!(dep[g]);
                (t2[g], y2[g]) = unstash(st[g], gm, i, t2[g], y2[g]);
            }
        }};
    }
    // Pushes column u (value v) for the lanes of vm of group g, spilling t3 where it is not a
    // hole.
    macro_rules! push {
        ($g:expr, $vm:expr, $u:expr, $v:expr) => {{
            let (g, vm) = ($g, $vm);
            let sm = _mm512_mask_cmpge_epi32_mask(vm, t3[g], zero_i);
            if sm != 0 {
                let i = idx!(dep[g]);
                stash(st[g], sm, i, t3[g], y3[g]);
                dep[g] = _mm512_mask_add_epi32(dep[g], sm, dep[g], one_i);
            }
            t3[g] = _mm512_mask_mov_epi32(t3[g], vm, t2[g]);
            y3[g] = _mm512_mask_mov_ps(y3[g], vm, y2[g]);
            t2[g] = _mm512_mask_mov_epi32(t2[g], vm, t1[g]);
            y2[g] = _mm512_mask_mov_ps(y2[g], vm, y1[g]);
            t1[g] = _mm512_mask_mov_epi32(t1[g], vm, _mm512_set1_epi32($u as i32));
            y1[g] = _mm512_mask_mov_ps(y1[g], vm, $v);
        }};
    }
    // Samples column u for every group, pops while t1 lies on or below the chord from the
    // sample to t2 (`$keep(x1, x2, y1, y2, v)`: the lanes keeping t1), and pushes the sample.
    // A round tests t1 against t2 and, where t1 goes and t3 is in a register, t2 against t3
    // (what the next round would test after popping t1), so it pops up to two vertices.
    macro_rules! step {
        ($u:expr, $track:expr, $keep:expr) => {{
            let u = $u;
            let c = f.cols[u as usize];
            let (mut vm, mut v) = ([0u16; G], [ninf; G]);
            let mut any = 0u16;
            for g in 0..G {
                (vm[g], v[g]) = sample!(c, g, u);
                any |= vm[g];
            }
            if any != 0 {
                let xp = _mm512_set1_ps(u as f32);
                if f.cc != 0.0 {
                    let drop = _mm512_set1_ps((f.cc * (u * u) as f64) as f32);
                    for g in 0..G {
                        v[g] = _mm512_sub_ps(v[g], drop);
                    }
                }
                let keep = $keep;
                let mut act = vm;
                loop {
                    let (mut p1, mut p2, mut more) = ([0u16; G], [0u16; G], [0u16; G]);
                    let mut anyp = 0u16;
                    for g in 0..G {
                        let has2 = _mm512_mask_cmpge_epi32_mask(act[g], t2[g], zero_i);
                        let x1 = _mm512_cvtepi32_ps(t1[g]);
                        let x2 = _mm512_cvtepi32_ps(t2[g]);
                        let x3 = _mm512_cvtepi32_ps(t3[g]);
                        p1[g] = has2 & !keep(x1, x2, y1[g], y2[g], v[g], xp);
                        let has3 = _mm512_mask_cmpge_epi32_mask(p1[g], t3[g], zero_i);
                        p2[g] = has3 & !keep(x2, x3, y2[g], y3[g], v[g], xp);
                        more[g] = p2[g] | (p1[g] & !has3);
                        anyp |= p1[g];
                    }
                    if anyp == 0 {
                        break;
                    }
                    let mut anym = 0u16;
                    for g in 0..G {
                        pop!(g, p1[g]);
                        if p2[g] != 0 {
                            pop!(g, p2[g]);
                        }
                        act[g] = more[g];
                        anym |= more[g];
                    }
                    if anym == 0 {
                        break;
                    }
                }
                for g in 0..G {
                    push!(g, vm[g], u, v[g]);
                    if $track {
                        hmax[g] = _mm512_mask_max_ps(hmax[g], vm[g], hmax[g], v[g]);
                    }
                }
            }
        }};
    }
    // Tangent walks. A query from the left (this azimuth) looks at slopes (y − hq)/(x − xq), one
    // from the right (the mirror azimuth, see `far_field_fast`) at (y − hq)/(xq − x): the same
    // compares with the abscissae's differences negated, and its curvature term is −2c'p.
    macro_rules! dx {
        ($x:expr, $xq:expr, $mir:expr) => {
            if $mir {
                _mm512_sub_ps($xq, $x)
            } else {
                _mm512_sub_ps($x, $xq)
            }
        };
    }
    // Tangent walks. A query from the left (this azimuth) looks at slopes (y − hq)/(x − xq), one
    // from the right (the mirror azimuth, see `far_field_fast`) at (y − hq)/(xq − x): the same
    // compares with the abscissae's differences negated, and its curvature term is −2c'p.
    //
    // The slope from a query to the vertices of a convex hull rises and then falls, so the
    // tangent is the first vertex whose successor does not rise, and whether one vertex's
    // successor rises does not depend on where the walk came from. So a walk compares several
    // pairs of consecutive vertices at once, independently, and takes the first that stops:
    // the same vertex, compared by the same operations, as a walk one vertex at a time, but
    // with one dependent round (and one loop exit) per [`WALK`] vertices rather than per
    // vertex.
    //
    // Whether the slope from the query to (nx, ny) is above that to (cx, cy), for the lanes
    // of `am` of group g.
    macro_rules! rises {
        ($am:expr, $g:expr, $xq:expr, $hq:expr, $mir:expr, $cx:expr, $cy:expr, $nx:expr, $ny:expr) => {{
            let lhs = _mm512_mul_ps(_mm512_sub_ps($ny, $hq[$g]), dx!($cx, $xq, $mir));
            let rhs = _mm512_mul_ps(_mm512_sub_ps($cy, $hq[$g]), dx!($nx, $xq, $mir));
            _mm512_mask_cmp_ps_mask::<_CMP_GT_OQ>($am, lhs, rhs)
        }};
    }
    // The tangent from the query (xq, hq) of groups' lanes qm, walked from the top of each
    // lane's stack: t1 (the vertex nearest the query), t2 and t3 compared in one round, then
    // [`WALK`] vertices of memory a round (independent gathers): per group its vertex (x, y).
    macro_rules! near_walk {
        ($xq:expr, $hq:expr, $qm:expr, $mir:expr) => {{
            let (xq, hq, qm) = ($xq, $hq, $qm);
            let (mut cur_x, mut cur_y) = ([ninf; G], [ninf; G]);
            let mut m = [0u16; G];
            let mut below = dep;
            let mut any = 0u16;
            for g in 0..G {
                let x1 = _mm512_cvtepi32_ps(t1[g]);
                let x2 = _mm512_cvtepi32_ps(t2[g]);
                let x3 = _mm512_cvtepi32_ps(t3[g]);
                let a1 = _mm512_mask_cmpge_epi32_mask(qm[g], t2[g], zero_i);
                let r1 = rises!(a1, g, xq, hq, $mir, x1, y1[g], x2, y2[g]);
                let v3 = _mm512_mask_cmpge_epi32_mask(r1, t3[g], zero_i);
                let r2 = rises!(v3, g, xq, hq, $mir, x2, y2[g], x3, y3[g]);
                cur_x[g] = _mm512_mask_mov_ps(_mm512_mask_mov_ps(x1, r1, x2), r2, x3);
                cur_y[g] = _mm512_mask_mov_ps(_mm512_mask_mov_ps(y1[g], r1, y2[g]), r2, y3[g]);
                m[g] = r2 | (r1 & !v3);
                any |= m[g];
            }
            while any != 0 {
                any = 0;
                for g in 0..G {
                    if m[g] == 0 {
                        continue;
                    }
                    let mut nt = [none; WALK];
                    let mut ny = [ninf; WALK];
                    let mut gm = [0u16; WALK];
                    for k in 0..WALK {
                        let kv = _mm512_set1_epi32(k as i32);
                        gm[k] = _mm512_mask_cmpgt_epi32_mask(m[g], below[g], kv);
                        let i = idx!(_mm512_sub_epi32(below[g], _mm512_set1_epi32(k as i32 + 1)));
                        (nt[k], ny[k]) = unstash(st[g], gm[k], i, none, ninf);
                    }
                    let (mut px, mut py) = (cur_x[g], cur_y[g]);
                    let mut r = 0xffffu16;
                    for k in 0..WALK {
                        let nx = _mm512_cvtepi32_ps(nt[k]);
                        r = rises!(r & gm[k], g, xq, hq, $mir, px, py, nx, ny[k]);
                        cur_x[g] = _mm512_mask_mov_ps(cur_x[g], r, nx);
                        cur_y[g] = _mm512_mask_mov_ps(cur_y[g], r, ny[k]);
                        (px, py) = (nx, ny[k]);
                    }
                    below[g] = _mm512_mask_sub_epi32(
                        below[g],
                        r,
                        below[g],
                        _mm512_set1_epi32(WALK as i32),
                    );
                    m[g] = r;
                    any |= r;
                }
            }
            (cur_x, cur_y)
        }};
    }
    // The same tangent walked from the bottom of each lane's stack (the vertex nearest a query
    // on the other side): memory rows 0 .. dep with plain loads, then the registers, [`WALK`]
    // vertices a round.
    macro_rules! far_walk {
        ($xq:expr, $hq:expr, $qm:expr, $mir:expr) => {{
            let (xq, hq, qm) = ($xq, $hq, $qm);
            // The registers' vertices bottom up: [t3, t2, t1] without the empty ones.
            let (mut r0t, mut r0y, mut r1t, mut r1y) = ([none; G], [ninf; G], [none; G], [ninf; G]);
            for g in 0..G {
                if qm[g] == 0 {
                    continue;
                }
                let has3 = _mm512_cmpge_epi32_mask(t3[g], zero_i);
                let has2 = _mm512_cmpge_epi32_mask(t2[g], zero_i);
                r0t[g] =
                    _mm512_mask_mov_epi32(_mm512_mask_mov_epi32(t1[g], has2, t2[g]), has3, t3[g]);
                r0y[g] = _mm512_mask_mov_ps(_mm512_mask_mov_ps(y1[g], has2, y2[g]), has3, y3[g]);
                r1t[g] = _mm512_mask_mov_epi32(t1[g], has3, t2[g]);
                r1y[g] = _mm512_mask_mov_ps(y1[g], has3, y2[g]);
            }
            // Vertex j of a lane's hull from the bottom, group g (t1 again past its last).
            let at = |g: usize, j: i32| -> (__m512i, __m512) {
                let jv = _mm512_set1_epi32(j);
                let k = _mm512_sub_epi32(jv, dep[g]);
                let (mut t, mut y) = (t1[g], y1[g]);
                let k1 = _mm512_cmpeq_epi32_mask(k, one_i);
                t = _mm512_mask_mov_epi32(t, k1, r1t[g]);
                y = _mm512_mask_mov_ps(y, k1, r1y[g]);
                let k0 = _mm512_cmpeq_epi32_mask(k, zero_i);
                t = _mm512_mask_mov_epi32(t, k0, r0t[g]);
                y = _mm512_mask_mov_ps(y, k0, r0y[g]);
                let mm = _mm512_cmpgt_epi32_mask(dep[g], jv);
                if mm != 0 {
                    let row = st[g].add(j as usize * FAR_LANES);
                    let lo = _mm512_maskz_loadu_epi64(mm as u8, row);
                    let hi = _mm512_maskz_loadu_epi64((mm >> 8) as u8, row.add(8));
                    (t, y) = unpack(mm, lo, hi, t, y);
                }
                (t, y)
            };
            let (mut cur_t, mut cur_y, mut cur_x) = ([none; G], [ninf; G], [ninf; G]);
            let mut m = qm;
            let mut any = 0u16;
            for g in 0..G {
                if qm[g] != 0 {
                    (cur_t[g], cur_y[g]) = at(g, 0);
                    cur_x[g] = _mm512_cvtepi32_ps(cur_t[g]);
                    any |= qm[g];
                }
            }
            let mut j = 0;
            while any != 0 {
                any = 0;
                for g in 0..G {
                    let mut r = m[g] & _mm512_cmpneq_epi32_mask(cur_t[g], t1[g]);
                    if r == 0 {
                        m[g] = 0;
                        continue;
                    }
                    let mut nv = [(none, ninf); WALK];
                    for k in 0..WALK {
                        nv[k] = at(g, j + 1 + k as i32);
                    }
                    let (mut pt, mut px, mut py) = (cur_t[g], cur_x[g], cur_y[g]);
                    for k in 0..WALK {
                        let (nt, ny) = nv[k];
                        let nx = _mm512_cvtepi32_ps(nt);
                        if k > 0 {
                            r &= _mm512_cmpneq_epi32_mask(pt, t1[g]);
                        }
                        r = rises!(r, g, xq, hq, $mir, px, py, nx, ny);
                        cur_t[g] = _mm512_mask_mov_epi32(cur_t[g], r, nt);
                        cur_x[g] = _mm512_mask_mov_ps(cur_x[g], r, nx);
                        cur_y[g] = _mm512_mask_mov_ps(cur_y[g], r, ny);
                        (pt, px, py) = (nt, nx, ny);
                    }
                    m[g] = r;
                    any |= r;
                }
                j += WALK as i32;
            }
            (cur_x, cur_y)
        }};
    }
    // A query's tangents from its walk's vertices into the slots `$sb` at query index `$k`:
    // stored (the first of its two parts, every group's lanes, −∞ where none) or joined by
    // max (the second, only the groups with lanes).
    macro_rules! put {
        ($sb:expr, $k:expr, $xq:expr, $hq:expr, $qm:expr, $corr:expr, $cur:expr, $mir:expr,
         $join:expr) => {{
            let (xq, hq, qm, corr, (cur_x, cur_y)) = ($xq, $hq, $qm, $corr, $cur);
            for g in 0..G {
                if $join && qm[g] == 0 {
                    continue;
                }
                let mut res = ninf;
                if qm[g] != 0 {
                    let slope =
                        _mm512_div_ps(_mm512_sub_ps(cur_y[g], hq[g]), dx!(cur_x[g], xq, $mir));
                    res = _mm512_mask_mov_ps(res, qm[g], _mm512_add_ps(slope, corr));
                }
                let p = $sb[g].add($k as usize * FAR_LANES);
                if $join {
                    let old = _mm512_loadu_ps(p);
                    res = _mm512_mask_max_ps(old, qm[g], old, res);
                }
                _mm512_storeu_ps(p, res);
            }
        }};
    }
    let blocked = f.r_steps.is_some();
    let blk = f.r_steps.map_or(i64::MAX, |(_, b)| b);
    let r = f.r_steps.map_or(0, |(r, _)| r);
    // The windows' first columns: this azimuth's q + N for q < W, the mirror's p − R' for its
    // query columns p = e − u', u' < W (the mirror exists only with a finite window).
    let (s_lo, s_hi) = match f.mirror {
        Some(e) => ((f.qoff + f.d).min(e - f.wa + 1 - r), (f.qoff + f.wa - 1 + f.d).max(e - r)),
        None => (f.d, f.wa - 1 + f.d),
    };
    // The suffix pass needs the samples up to the end of the block of the last window.
    let last = if blocked { (s_hi / blk + 1) * blk - 1 } else { f.len - 1 };
    // With two passes (a finite window), every sample they read (columns s_lo ..) and every
    // query's height is copied first into contiguous scratch, a few hundred KiB that stay in
    // L2. In the sweeps, a chain of dependent compares and branches, those loads waited for
    // memory even prefetched (at 2048², the sample and height loads and their prefetches were
    // a fifth of the sweeps' profile, at 512², all in L2, a twentieth); this loop has no chain,
    // so its misses overlap, and each column is read once for both passes. Measured at 2048²,
    // 32 bins (interleaved timing binaries, best of three, with the chunked major lines): the
    // build's CPU time −11 % at `unlimited` with `edge=wrap`, −17 % at R = 64. With one pass
    // (`edge=none` unlimited) the copy cost more than it saved (+8 %), so that pass reads the
    // major lines itself, prefetched.
    pub(super) const PF: i64 = 24;
    for u in s_lo.max(0)..f.len {
        if !copied {
            break;
        }
        prefetch!(u + PF);
        let c = f.cols[u as usize];
        for g in 0..G {
            if lanes_at!(c, g) != 0 {
                _mm512_storeu_ps(ss.add((u as usize * G + g) * FAR_LANES), lerp_at!(c, g));
            }
        }
    }
    for (mir, qcs) in [(0, f.qs), (1, f.mq)] {
        if !copied {
            break;
        }
        for (k, qc) in qcs.iter().enumerate() {
            if !qc.on {
                continue;
            }
            // This azimuth's query column k sits at column qoff + k, the mirror's at e − k.
            let q = if mir == 0 { f.qoff + k as i64 } else { f.mirror.unwrap_or(0) - k as i64 };
            let row = sh.add((k * 2 + mir) * G * FAR_LANES);
            for g in 0..G {
                let (tm, b0) = texels_at(f, i0[g], nl[g], qc.shift);
                if tm != 0 {
                    _mm512_storeu_ps(row.add(g * FAR_LANES), load_h0!(q, b0));
                }
            }
        }
    }
    // Suffix (or whole-line) pass, right to left.
    for up in (s_lo..=last.min(f.len - 1)).rev() {
        if blocked && up % blk == blk - 1 {
            reset!();
        }
        if !copied {
            // The queries' heights (the first to touch a row; the samples read it N later).
            prefetch!(up - f.d - 12);
        }
        // Keep t1 where the slope p→t1 is above t1→t2.
        step!(up, false, |x1: __m512,
                          x2: __m512,
                          y1: __m512,
                          y2: __m512,
                          v: __m512,
                          xp: __m512| {
            let lhs = _mm512_mul_ps(_mm512_sub_ps(y1, v), _mm512_sub_ps(x2, x1));
            let rhs = _mm512_mul_ps(_mm512_sub_ps(y2, y1), _mm512_sub_ps(x1, xp));
            _mm512_cmp_ps_mask::<_CMP_GT_OQ>(lhs, rhs)
        });
        // This azimuth's query whose window starts here (query column q, on column q + qoff).
        let q = up - f.d - f.qoff;
        if (0..f.wa).contains(&q) && f.qs[q as usize].on {
            let (xq, corr, qm, hq) = query_at!(up - f.d, f.qs[q as usize], false, q);
            let cur = near_walk!(xq, hq, qm, false);
            put!(sb, q, xq, hq, qm, corr, cur, false, false);
        }
        if let Some(e) = f.mirror {
            // The mirror's query whose window starts here: its hull is this suffix, seen from
            // the right, so walked from the bottom (the block's end).
            let p = up + r;
            let k = e - p;
            if (0..f.wa).contains(&k) && f.mq[k as usize].on {
                let (xq, corr, qm, hq) = query_at!(p, f.mq[k as usize], true, k);
                let cur = far_walk!(xq, hq, qm, true);
                put!(sbm, k, xq, hq, qm, corr, cur, true, false);
            }
        }
    }
    if !blocked {
        return;
    }
    // Prefix pass, left to right: a window's part in the next block, so only blocks after the
    // first window's start. This azimuth's queries walk each lane's hull from its bottom (the
    // block's first sample, never popped), the mirror's from its top.
    reset!();
    let mut next = (s_lo / blk + 1) * blk;
    let end = match f.mirror {
        Some(e) => (f.qoff + f.wa - 1 + r).max(e - f.d),
        None => f.wa - 1 + r,
    }
    .min(f.len - 1);
    macro_rules! advance {
        ($to:expr) => {{
            let to = $to;
            while next <= to {
                if next % blk == 0 {
                    reset!();
                }
                // Keep t1 where the slope t2→t1 is above t1→p.
                step!(next, true, |x1: __m512,
                                   x2: __m512,
                                   y1: __m512,
                                   y2: __m512,
                                   v: __m512,
                                   xp: __m512| {
                    let lhs = _mm512_mul_ps(_mm512_sub_ps(y1, y2), _mm512_sub_ps(xp, x1));
                    let rhs = _mm512_mul_ps(_mm512_sub_ps(v, y1), _mm512_sub_ps(x1, x2));
                    _mm512_cmp_ps_mask::<_CMP_GT_OQ>(lhs, rhs)
                });
                if let Some(e) = f.mirror {
                    // The mirror's query whose window ends here, when it reaches back into
                    // the previous block.
                    let p = next + f.d;
                    let k = e - p;
                    if (0..f.wa).contains(&k)
                        && f.mq[k as usize].on
                        && (next - blk + 1) / blk < next / blk
                    {
                        let (xq, corr, qm, hq) = query_at!(p, f.mq[k as usize], true, k);
                        if qm.iter().any(|&m| m != 0) {
                            let cur = near_walk!(xq, hq, qm, true);
                            put!(sbm, k, xq, hq, qm, corr, cur, true, true);
                        }
                    }
                }
                next += 1;
            }
        }};
    }
    for q in 0..f.wa {
        let qc = f.qoff + q;
        let top = (qc + r).min(f.len - 1);
        advance!(top);
        if !f.qs[q as usize].on {
            continue;
        }
        // Only when the window reaches into the next block (see `far_field`).
        if top / blk <= (qc + f.d) / blk {
            continue;
        }
        let (xq, corr, mut qm, hq) = query_at!(qc, f.qs[q as usize], false, q);
        if qm.iter().all(|&m| m == 0) {
            continue;
        }
        // This part of the window is the far one (it starts at the block's first column, bs):
        // the lanes whose tangent from the suffix part (already in the slot) no vertex here can
        // beat skip the walk. A vertex's slope is at most (hmax − hq)/D + corr, with D the
        // distance from bs where the numerator is positive and from `top` where it is not;
        // computed by the same float operations on larger operands, so a bound by rounding too.
        let bs = top / blk * blk;
        let dmin = _mm512_set1_ps((bs - qc) as f32);
        let dmax = _mm512_set1_ps((top - qc) as f32);
        let zero = _mm512_setzero_ps();
        for g in 0..G {
            if qm[g] == 0 {
                continue;
            }
            let a = _mm512_sub_ps(hmax[g], hq[g]);
            let d = _mm512_mask_mov_ps(dmax, _mm512_cmp_ps_mask::<_CMP_GT_OQ>(a, zero), dmin);
            let bound = _mm512_add_ps(_mm512_div_ps(a, d), corr);
            let old = _mm512_loadu_ps(sb[g].add(q as usize * FAR_LANES));
            qm[g] &= !_mm512_cmp_ps_mask::<_CMP_LE_OQ>(bound, old);
        }
        if qm.iter().all(|&m| m == 0) {
            continue;
        }
        let cur = far_walk!(xq, hq, qm, false);
        put!(sb, q, xq, hq, qm, corr, cur, false, true);
    }
    advance!(end);
}

/// The tangents of a batch of groups (slots `slot0`.. of `sb`, groups `batch[g]` = (i0, lines))
/// into the sums, in one pass of independent adds (interleaved with the hull work, every add
/// waited for its cache misses), query column by query column. Each column's sums are a new
/// row of the plane, so one group alone touches a page per column; the groups of a batch are
/// neighbours across the lines, so at each column they add into one run of the row: one page
/// and a few adjacent cache lines for the whole batch. A texel's two roles weigh 1 in all, so
/// only when a role finds nothing ahead (rare) is the other's weight, then the texel's whole
/// valid weight, listed (`miss`; both missing sum to 1 over a sum of 0).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
pub(super) unsafe fn add_batch_avx512(
    f: &Family<'_>,
    batch: &[(i64, u32)],
    slot0: usize,
    sums: &mut [f32],
    sb: &[f32],
    miss: &mut Vec<Miss>,
) {
    use std::arch::x86_64::*;
    let ninf = _mm512_set1_ps(f32::NEG_INFINITY);
    let wa = f.wa as usize;
    pub(super) const PFS: i64 = 24;
    let Some(&(first, _)) = batch.first() else { return };
    let span = batch.last().map_or(0, |&(i0, _)| i0 + FAR_LANES as i64 - first);
    for q in 0..f.wa {
        // Each query column's sums are a new row: fetch a few ahead, every cache line of the
        // batch's run of it.
        let qa = q + PFS;
        if qa < f.wa && f.qs[qa as usize].on {
            let b_lo = first - f.qs[qa as usize].shift;
            for off in (0..span + 16).step_by(16) {
                let b = b_lo + off;
                let b = if f.wrap { b.rem_euclid(f.hb) } else { b.clamp(0, f.hb - 1) };
                let p = sums.as_ptr().wrapping_add(f.lay.at(f.abase[qa as usize], b as usize));
                _mm_prefetch::<_MM_HINT_T0>(p as *const i8);
            }
        }
        let qc = f.qs[q as usize];
        if !qc.on {
            continue;
        }
        let wt = _mm512_set1_ps(qc.wt * f.inv_step);
        for (g, &(i0, nl)) in batch.iter().enumerate() {
            let (tm, b0) = texels_at(f, i0, nl, qc.shift);
            let res = _mm512_loadu_ps(sb.as_ptr().add(((slot0 + g) * wa + q as usize) * FAR_LANES));
            let got = tm & _mm512_cmp_ps_mask::<_CMP_GT_OQ>(res, ninf);
            if got != 0 {
                add_lanes(f, q, b0, got, _mm512_mul_ps(wt, res), sums);
            }
            if tm & !got != 0 {
                let (runs, n) = lane_runs(f, b0, tm & !got);
                for &(mm, o) in &runs[..n] {
                    let at = f.abase[q as usize] as isize + o;
                    let lanes = (0..16).filter(|l| mm >> l & 1 == 1);
                    miss.extend(lanes.map(|l| Miss { at: (at + l) as usize, wt: qc.other }));
                }
            }
        }
    }
}

/// Adds `v` in the lanes of `m` (texels b0 + lane of query column q) to `dst` (major-line
/// layout; with `edge=wrap` the lanes past the minor end wrap to its start).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
pub(super) unsafe fn add_lanes(
    f: &Family<'_>,
    q: i64,
    b0: i64,
    m: u16,
    v: std::arch::x86_64::__m512,
    dst: &mut [f32],
) {
    use std::arch::x86_64::*;
    let base = f.abase[q as usize] as isize;
    let (runs, n) = lane_runs(f, b0, m);
    for &(mm, o) in &runs[..n] {
        // Masked lanes are neither read nor written, so the pointer may point before the
        // slice for lanes that are masked off.
        let p = dst.as_mut_ptr().wrapping_offset(base + o);
        let old = _mm512_maskz_loadu_ps(mm, p);
        _mm512_mask_storeu_ps(p, mm, _mm512_add_ps(old, v));
    }
}

/// Where the lanes of `m` (texels b0 + lane of a query column) lie in the sums: up to four
/// runs (mask, offset of lane 0 from the column's base), none empty, the first `n` of them.
/// With `edge=wrap` the lanes b0 + l ≥ hb belong hb earlier; in chunks ([`SumLayout`]), the
/// lanes from the next chunk's first texel on are that chunk's.
#[inline(always)]
pub(super) fn lane_runs(f: &Family<'_>, b0: i64, m: u16) -> ([(u16, isize); 4], usize) {
    let hi = if b0 + 16 > f.hb { lane_range(b0 - f.hb, f.hb, 16) } else { 0 };
    let mut runs = [(0u16, 0isize); 4];
    let mut n = 0;
    for (mm, off) in [(m & !hi, b0), (m & hi, b0 - f.hb)] {
        if mm == 0 {
            continue;
        }
        let parts = if f.lay.chunk == 0 {
            [(mm, off as isize), (0, 0)]
        } else {
            let (c, r) = (off.div_euclid(SUM_CHUNK as i64), off.rem_euclid(SUM_CHUNK as i64));
            let k = SUM_CHUNK as i64 - r;
            let lo = if k >= 16 { 0xffff } else { ((1u32 << k) - 1) as u16 };
            let at = |c: i64| c as isize * f.lay.chunk as isize + r as isize;
            [(mm & lo, at(c)), (mm & !lo, at(c + 1) - SUM_CHUNK as isize)]
        };
        for part in parts.into_iter().filter(|p| p.0 != 0) {
            runs[n] = part;
            n += 1;
        }
    }
    (runs, n)
}
