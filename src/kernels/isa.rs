//! Which instruction set a kernel's hot loop is compiled for, chosen at run time.
//!
//! The release binary is built for the baseline x86-64 (no `-C target-cpu`), so it runs on any
//! CPU; the hot loops of `lengyel`, `exact`, `march` and `sweep` are compiled a second and a
//! third time with AVX-512 and AVX2+FMA enabled, and a kernel picks the best variant the CPU has
//! once, when it is built ([`Isa::detect`]). Tests and benches can ask for a variant
//! ([`Isa::supported`] says whether this CPU can run it) and compare the variants' outputs.
//!
//! [`Isa::run`] is the one `#[target_feature]` wrapper every kernel uses: it calls a closure
//! from inside a function compiled for the variant, so the `#[inline(always)]` body the closure
//! calls is compiled for that instruction set. Other architectures run the baseline only.

/// Which compiled variant of the hot loops this CPU runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Isa {
    Avx512,
    Avx2,
    Baseline,
}

impl Isa {
    /// The best variant the running CPU supports.
    pub fn detect() -> Isa {
        [Isa::Avx512, Isa::Avx2].into_iter().find(|i| i.supported()).unwrap_or(Isa::Baseline)
    }

    /// Whether the running CPU has every feature this variant was compiled for.
    pub fn supported(self) -> bool {
        #[cfg(target_arch = "x86_64")]
        {
            match self {
                Isa::Avx512 => is_x86_feature_detected!("avx512f"),
                Isa::Avx2 => is_x86_feature_detected!("avx2") && is_x86_feature_detected!("fma"),
                Isa::Baseline => true,
            }
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            self == Isa::Baseline
        }
    }

    /// `self`, or the best supported variant when this CPU lacks it.
    pub fn or_detected(self) -> Isa {
        if self.supported() {
            self
        } else {
            Isa::detect()
        }
    }

    /// The narrower of two variants (AVX-512 ⊃ AVX2+FMA ⊃ baseline).
    pub fn min(self, other: Isa) -> Isa {
        let rank = |i: Isa| match i {
            Isa::Avx512 => 2,
            Isa::Avx2 => 1,
            Isa::Baseline => 0,
        };
        if rank(self) <= rank(other) {
            self
        } else {
            other
        }
    }

    /// Runs `f` inside a function compiled with this variant's features, so what `f` inlines
    /// (an `#[inline(always)]` hot loop) is compiled for them.
    ///
    /// # Safety
    /// The running CPU must support this variant ([`Isa::supported`]); kernels only hold a
    /// variant they checked.
    #[inline(always)]
    pub unsafe fn run<R>(self, f: impl FnOnce() -> R) -> R {
        #[cfg(target_arch = "x86_64")]
        match self {
            // SAFETY: the caller guarantees the CPU has the variant's features.
            Isa::Avx512 => unsafe { with_avx512(f) },
            Isa::Avx2 => unsafe { with_avx2(f) },
            Isa::Baseline => f(),
        }
        #[cfg(not(target_arch = "x86_64"))]
        f()
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx2,fma")]
unsafe fn with_avx512<R>(f: impl FnOnce() -> R) -> R {
    f()
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn with_avx2<R>(f: impl FnOnce() -> R) -> R {
    f()
}
