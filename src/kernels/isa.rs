//! Which instruction set a kernel's hot loop is compiled for, chosen at run time.
//!
//! The release binary is built for the baseline x86-64 (no `-C target-cpu`), so it runs on any
//! CPU; the hot loops of `lengyel`, `exact`, `march` and `sweep` are compiled a second and a
//! third time with AVX-512 and AVX2+FMA enabled, and a kernel picks the best variant the CPU has
//! once, when it is built ([`Isa::detect`]). Tests and benches can ask for a variant
//! ([`Isa::supported`] says whether this CPU can run it) and compare the variants' outputs.
//!
//! Each kernel has its own two small `#[target_feature]` wrappers that call its
//! `#[inline(always)]` hot loop, so LLVM compiles the loop for that instruction set. One generic
//! wrapper taking a closure was tried: LLVM did not always inline the closure into it, and the
//! loop then ran as baseline code (`march` 40× slower, docs/architecture.md). Other
//! architectures run the baseline only.

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
}
