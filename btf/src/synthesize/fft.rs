//! A small radix-2 complex FFT in 2D (f64), for quilting's overlap-error search: the
//! squared error of a block's overlap against every exemplar position is a sum of
//! cross-correlations, which the FFT computes for all positions at once
//! (`O(N log N)` instead of `O(N · overlap)` per block).
//!
//! Sequential by design: callers run independent transforms in parallel, and one
//! transform's arithmetic order never depends on the thread count.

use std::f64::consts::PI;

#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct C64 {
    pub re: f64,
    pub im: f64,
}

impl C64 {
    #[inline]
    pub fn new(re: f64, im: f64) -> Self {
        C64 { re, im }
    }
    #[inline]
    fn mul(self, o: C64) -> C64 {
        C64::new(self.re * o.re - self.im * o.im, self.re * o.im + self.im * o.re)
    }
    /// `conj(self) · o`
    #[inline]
    pub fn conj_mul(self, o: C64) -> C64 {
        C64::new(self.re * o.re + self.im * o.im, self.re * o.im - self.im * o.re)
    }
}

struct Plan1 {
    n: usize,
    tw: Vec<C64>,
    rev: Vec<u32>,
}

impl Plan1 {
    fn new(n: usize) -> Self {
        assert!(n.is_power_of_two());
        let bits = n.trailing_zeros();
        let tw = (0..n / 2)
            .map(|j| {
                let a = -2.0 * PI * j as f64 / n as f64;
                C64::new(a.cos(), a.sin())
            })
            .collect();
        let rev = (0..n as u32)
            .map(|i| if bits == 0 { 0 } else { i.reverse_bits() >> (32 - bits) })
            .collect();
        Plan1 { n, tw, rev }
    }

    fn run(&self, a: &mut [C64], inverse: bool) {
        let n = self.n;
        for i in 0..n {
            let j = self.rev[i] as usize;
            if i < j {
                a.swap(i, j);
            }
        }
        let mut len = 2;
        while len <= n {
            let half = len / 2;
            let step = n / len;
            for start in (0..n).step_by(len) {
                for j in 0..half {
                    let mut w = self.tw[j * step];
                    if inverse {
                        w.im = -w.im;
                    }
                    let u = a[start + j];
                    let v = a[start + j + half].mul(w);
                    a[start + j] = C64::new(u.re + v.re, u.im + v.im);
                    a[start + j + half] = C64::new(u.re - v.re, u.im - v.im);
                }
            }
            len *= 2;
        }
    }
}

/// A 2D transform of `nx × ny` (both powers of two), row-major data.
pub struct Fft2 {
    pub nx: usize,
    pub ny: usize,
    px: Plan1,
    py: Plan1,
}

impl Fft2 {
    pub fn new(nx: usize, ny: usize) -> Self {
        Fft2 {
            nx,
            ny,
            px: Plan1::new(nx),
            py: Plan1::new(ny),
        }
    }

    /// Forward transform; rows at or beyond `rows_nonzero` must be zero (they are skipped
    /// in the row pass: a block template occupies only its first rows).
    pub fn forward(&self, a: &mut [C64], rows_nonzero: usize) {
        for r in 0..rows_nonzero.min(self.ny) {
            self.px.run(&mut a[r * self.nx..(r + 1) * self.nx], false);
        }
        self.columns(a, false);
    }

    /// Inverse transform (scaled by 1/(nx·ny)); only rows `< rows_needed` of the result
    /// are computed, the others are left in an unspecified state.
    pub fn inverse(&self, a: &mut [C64], rows_needed: usize) {
        self.columns(a, true);
        let s = 1.0 / (self.nx * self.ny) as f64;
        for r in 0..rows_needed.min(self.ny) {
            let row = &mut a[r * self.nx..(r + 1) * self.nx];
            self.px.run(row, true);
            for v in row.iter_mut() {
                v.re *= s;
                v.im *= s;
            }
        }
    }

    fn columns(&self, a: &mut [C64], inverse: bool) {
        let (nx, ny) = (self.nx, self.ny);
        // Eight columns at a time: one gather pass reads whole cache lines.
        const G: usize = 8;
        let mut buf = vec![C64::default(); ny * G];
        let mut c0 = 0;
        while c0 < nx {
            let g = G.min(nx - c0);
            for r in 0..ny {
                for k in 0..g {
                    buf[k * ny + r] = a[r * nx + c0 + k];
                }
            }
            for k in 0..g {
                self.py.run(&mut buf[k * ny..(k + 1) * ny], inverse);
            }
            for r in 0..ny {
                for k in 0..g {
                    a[r * nx + c0 + k] = buf[k * ny + r];
                }
            }
            c0 += g;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn circular_correlation_matches_direct_sum() {
        let (nx, ny) = (16, 8);
        let f: Vec<f64> = (0..nx * ny).map(|i| ((i * 37 % 11) as f64 - 5.0) * 0.3).collect();
        let t: Vec<f64> = (0..nx * ny)
            .map(|i| if i % nx < 3 && i / nx < 2 { (i % 7) as f64 } else { 0.0 })
            .collect();
        let fft = Fft2::new(nx, ny);
        let mut a: Vec<C64> = f.iter().map(|&v| C64::new(v, 0.0)).collect();
        let mut b: Vec<C64> = t.iter().map(|&v| C64::new(v, 0.0)).collect();
        fft.forward(&mut a, ny);
        fft.forward(&mut b, 2);
        let mut c: Vec<C64> = b.iter().zip(&a).map(|(x, y)| x.conj_mul(*y)).collect();
        fft.inverse(&mut c, ny);
        for py in 0..ny {
            for px in 0..nx {
                let mut s = 0.0;
                for qy in 0..ny {
                    for qx in 0..nx {
                        s += t[qy * nx + qx] * f[((py + qy) % ny) * nx + (px + qx) % nx];
                    }
                }
                assert!(
                    (c[py * nx + px].re - s).abs() < 1e-9,
                    "{px},{py}: {} vs {s}",
                    c[py * nx + px].re
                );
            }
        }
    }
}
