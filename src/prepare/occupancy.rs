//! Occupied cells of a small box of the integer grid, one bit each, for the prepare steps that
//! look cells up by their coordinates (the voxel grid, the cluster step).
//!
//! A frame's cloud after the crop spans a few hundred thousand cells of a few centimetres: a
//! bitmap of tens of kilobytes, where hashing every point's cell or sorting the cells costs more
//! than the steps' own work. Bits run in grid order (z fastest, then y, then x), and each word
//! knows how many occupied cells come before it, so an occupied cell's rank (its index among the
//! occupied cells in grid order) is one popcount away, and the cells one or two apart along z are
//! a few bits of one or two words.

/// Cells of margin on every side of the cloud's box: every cell up to this far from an occupied
/// one has a bit.
const MARGIN: i64 = 2;

/// The bitmap may take at most this many 64-bit words per cell it is built for (plus a floor for
/// small clouds); beyond, zeroing and counting the words costs more than sorting the cells, and
/// the caller sorts instead.
const WORDS_PER_CELL: usize = 16;
const WORDS_FLOOR: usize = 4096;

pub(super) struct Occupancy {
    /// The box's lowest cell and its size in cells along each axis.
    low: [i64; 3],
    size: [usize; 3],
    words: Vec<u64>,
    /// Per word, how many occupied cells come before it (see [`Occupancy::count`]).
    before: Vec<u32>,
}

impl Occupancy {
    /// The box around `cells` with [`MARGIN`] on every side, every cell of `cells` occupied; None
    /// when its bitmap would be too large for the number of cells (see [`WORDS_PER_CELL`]) or
    /// `cells` is empty. Coordinates must be far inside i64 (the callers keep them under 2^40).
    pub fn of(cells: &[[i64; 3]]) -> Option<Self> {
        let first = cells.first()?;
        let (low, high) = cells.iter().fold((*first, *first), |(low, high), k| {
            (
                [0, 1, 2].map(|a| low[a].min(k[a])),
                [0, 1, 2].map(|a| high[a].max(k[a])),
            )
        });
        let low = low.map(|c| c - MARGIN);
        let size = [0, 1, 2].map(|a| usize::try_from(high[a] + MARGIN - low[a] + 1).ok());
        let [Some(x), Some(y), Some(z)] = size else { return None };
        let bits = x.checked_mul(y)?.checked_mul(z)?;
        let words = bits.div_ceil(64);
        if words > WORDS_PER_CELL * cells.len() + WORDS_FLOOR {
            return None;
        }
        let mut grid = Self {
            low,
            size: [x, y, z],
            words: vec![0; words],
            before: Vec::new(),
        };
        for k in cells {
            let at = grid.position(*k);
            grid.words[at >> 6] |= 1 << (at & 63);
        }
        grid.count();
        Some(grid)
    }

    /// Where cell `k` (inside the box) lies in grid order.
    pub fn position(&self, k: [i64; 3]) -> usize {
        let r = [0, 1, 2].map(|a| (k[a] - self.low[a]) as usize);
        (r[0] * self.size[1] + r[1]) * self.size[2] + r[2]
    }

    /// How far apart in grid order two cells one step apart along x, y and z are.
    pub fn strides(&self) -> [isize; 3] {
        [(self.size[1] * self.size[2]) as isize, self.size[2] as isize, 1]
    }

    /// Fills `before`.
    fn count(&mut self) {
        let mut total = 0u32;
        self.before = self
            .words
            .iter()
            .map(|&w| {
                let here = total;
                // Most words of a frame's box are empty (and a popcount is a dozen instructions
                // where the CPU has no instruction for it).
                if w != 0 {
                    total += w.count_ones();
                }
                here
            })
            .collect();
    }

    /// How many cells are occupied.
    pub fn occupied(&self) -> usize {
        match (self.before.last(), self.words.last()) {
            (Some(b), Some(w)) => (*b + w.count_ones()) as usize,
            _ => 0,
        }
    }

    /// The index, among the occupied cells in grid order, of the occupied cell at `at`.
    pub fn rank(&self, at: usize) -> u32 {
        let below = self.words[at >> 6] & ((1u64 << (at & 63)) - 1);
        self.before[at >> 6] + below.count_ones()
    }

    /// Which of the `len` (1 to 57) cells from `at` on in grid order are occupied: bit i for the
    /// cell at `at + i`. Every cell within [`MARGIN`] of an occupied one may be asked for.
    pub fn window(&self, at: usize, len: u32) -> u64 {
        let (word, bit) = (at >> 6, (at & 63) as u32);
        let mut bits = self.words[word] >> bit;
        if bit + len > 64 {
            bits |= self.words[word + 1] << (64 - bit);
        }
        bits & ((1u64 << len) - 1)
    }
}
