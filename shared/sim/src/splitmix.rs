//! The sim's one random generator (SplitMix64): small, portable and seedable, so layouts and
//! perturbations are identical on every platform, including wasm32.

pub(crate) struct SplitMix64(pub(crate) u64);

impl SplitMix64 {
    pub(crate) fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1).
    pub(crate) fn next_f32(&mut self) -> f32 {
        (self.next_u64() >> 40) as f32 / (1u64 << 24) as f32
    }

    pub(crate) fn range(&mut self, low: f32, high: f32) -> f32 {
        low + (high - low) * self.next_f32()
    }

    /// 1 or -1 with even odds: which side of the arm something stands on.
    pub(crate) fn side(&mut self) -> f32 {
        if self.next_f32() < 0.5 { 1.0 } else { -1.0 }
    }

    /// Standard normal (Box-Muller; the first draw is shifted off zero so its logarithm is finite).
    pub(crate) fn gaussian(&mut self) -> f32 {
        let u = (self.next_f32() + f32::EPSILON).min(1.0);
        let v = self.next_f32();
        (-2.0 * u.ln()).sqrt() * (std::f32::consts::TAU * v).cos()
    }
}
