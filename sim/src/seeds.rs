//! Seed derivation: every mesh, subject and frame gets its own seed from the run's seed and its
//! indices, so output is identical whatever the thread count or generation order.

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

/// SplitMix64 finaliser: a cheap, well-mixed hash of one word.
fn mix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// A seed for the item at `path` (e.g. `[family, subject, pose]`) under `root`.
pub fn derive(root: u64, path: &[u64]) -> u64 {
    path.iter().fold(mix(root), |acc, &part| mix(acc ^ mix(part)))
}

pub fn rng(seed: u64) -> ChaCha8Rng {
    ChaCha8Rng::seed_from_u64(seed)
}
