//! A small SVG scatter plot on log–log axes, for the `gonio bench` reports (error against
//! run time). Written out by hand because a plotting dependency would be paid by every
//! build for two pictures; the output opens in any browser.

use std::fmt::Write as _;

/// One set of points drawn in one colour and joined in the given order.
pub struct Series {
    pub name: String,
    /// (x, y, label) — both coordinates must be positive (log axes); others are skipped.
    pub points: Vec<(f64, f64, String)>,
}

const COLOURS: [&str; 6] = ["#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b"];

/// Log–log scatter of `series` with axis titles; points are labelled with their text.
pub fn log_log(title: &str, x_title: &str, y_title: &str, series: &[Series]) -> String {
    let (w, h, left, right, top, bottom) = (760.0, 480.0, 70.0, 200.0, 40.0, 50.0);
    let pts = || {
        series
            .iter()
            .flat_map(|s| s.points.iter())
            .filter(|p| p.0 > 0.0 && p.1 > 0.0 && p.0.is_finite() && p.1.is_finite())
    };
    let decade = |v: f64, up: bool| {
        if up {
            10f64.powf(v.log10().ceil())
        } else {
            10f64.powf(v.log10().floor())
        }
    };
    let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for p in pts() {
        x0 = x0.min(p.0);
        x1 = x1.max(p.0);
        y0 = y0.min(p.1);
        y1 = y1.max(p.1);
    }
    let mut s = String::new();
    let _ = writeln!(
        s,
        "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{w}\" height=\"{h}\" font-family=\"sans-serif\" font-size=\"11\">"
    );
    let _ = writeln!(s, "<rect width=\"100%\" height=\"100%\" fill=\"white\"/>");
    let _ = writeln!(s, "<text x=\"{left}\" y=\"22\" font-size=\"14\">{}</text>", esc(title));
    if x0 > x1 {
        let _ = writeln!(s, "<text x=\"{left}\" y=\"100\">no data</text></svg>");
        return s;
    }
    let (x0, x1) = (decade(x0, false), decade(x1, true).max(decade(x0, false) * 10.0));
    let (y0, y1) = (decade(y0, false), decade(y1, true).max(decade(y0, false) * 10.0));
    let (pw, ph) = (w - left - right, h - top - bottom);
    let px = |x: f64| left + (x.log10() - x0.log10()) / (x1.log10() - x0.log10()) * pw;
    let py = |y: f64| top + ph - (y.log10() - y0.log10()) / (y1.log10() - y0.log10()) * ph;
    let _ = writeln!(
        s,
        "<rect x=\"{left}\" y=\"{top}\" width=\"{pw}\" height=\"{ph}\" fill=\"none\" stroke=\"#444\"/>"
    );
    for (lo, hi, horizontal) in [(x0, x1, true), (y0, y1, false)] {
        let mut d = lo;
        while d <= hi * 1.0001 {
            if horizontal {
                let x = px(d);
                let _ = writeln!(
                    s,
                    "<line x1=\"{x:.1}\" y1=\"{top}\" x2=\"{x:.1}\" y2=\"{:.1}\" stroke=\"#ddd\"/>",
                    top + ph
                );
                let _ = writeln!(
                    s,
                    "<text x=\"{x:.1}\" y=\"{:.1}\" text-anchor=\"middle\">{d:e}</text>",
                    top + ph + 16.0
                );
            } else {
                let y = py(d);
                let _ = writeln!(
                    s,
                    "<line x1=\"{left}\" y1=\"{y:.1}\" x2=\"{:.1}\" y2=\"{y:.1}\" stroke=\"#ddd\"/>",
                    left + pw
                );
                let _ = writeln!(
                    s,
                    "<text x=\"{:.1}\" y=\"{:.1}\" text-anchor=\"end\">{d:e}</text>",
                    left - 4.0,
                    y + 4.0
                );
            }
            d *= 10.0;
        }
    }
    let _ = writeln!(
        s,
        "<text x=\"{:.1}\" y=\"{:.1}\" text-anchor=\"middle\">{}</text>",
        left + pw / 2.0,
        h - 10.0,
        esc(x_title)
    );
    let _ = writeln!(
        s,
        "<text transform=\"translate(16,{:.1}) rotate(-90)\" text-anchor=\"middle\">{}</text>",
        top + ph / 2.0,
        esc(y_title)
    );
    for (k, ser) in series.iter().enumerate() {
        let c = COLOURS[k % COLOURS.len()];
        let good: Vec<_> = ser
            .points
            .iter()
            .filter(|p| p.0 > 0.0 && p.1 > 0.0 && p.0.is_finite() && p.1.is_finite())
            .collect();
        if good.len() > 1 {
            let path: Vec<String> = good.iter().map(|p| format!("{:.1},{:.1}", px(p.0), py(p.1))).collect();
            let _ = writeln!(
                s,
                "<polyline points=\"{}\" fill=\"none\" stroke=\"{c}\"/>",
                path.join(" ")
            );
        }
        for p in &good {
            let (x, y) = (px(p.0), py(p.1));
            let _ = writeln!(s, "<circle cx=\"{x:.1}\" cy=\"{y:.1}\" r=\"4\" fill=\"{c}\"/>");
            let _ = writeln!(
                s,
                "<text x=\"{:.1}\" y=\"{:.1}\" fill=\"{c}\">{}</text>",
                x + 6.0,
                y - 4.0,
                esc(&p.2)
            );
        }
        let ly = top + 14.0 + 18.0 * k as f64;
        let lx = left + pw + 12.0;
        let _ = writeln!(
            s,
            "<circle cx=\"{lx:.1}\" cy=\"{:.1}\" r=\"4\" fill=\"{c}\"/>",
            ly - 4.0
        );
        let _ = writeln!(s, "<text x=\"{:.1}\" y=\"{ly:.1}\">{}</text>", lx + 8.0, esc(&ser.name));
    }
    s.push_str("</svg>\n");
    s
}

fn esc(t: &str) -> String {
    t.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_marker_per_positive_point_and_a_legend_per_series() {
        let s = log_log(
            "t",
            "x",
            "y",
            &[
                Series {
                    name: "a<b".into(),
                    points: vec![
                        (1.0, 0.1, "p".into()),
                        (10.0, 0.01, "q".into()),
                        (0.0, 1.0, "bad".into()),
                    ],
                },
                Series {
                    name: "c".into(),
                    points: vec![(5.0, 0.05, "r".into())],
                },
            ],
        );
        // 3 plotted points + 2 legend markers.
        assert_eq!(s.matches("<circle").count(), 5);
        assert!(s.contains("a&lt;b"));
        assert!(!s.contains(">bad<"));
        assert_eq!(s.matches("<polyline").count(), 1);
    }

    #[test]
    fn empty_input_says_so() {
        assert!(log_log("t", "x", "y", &[]).contains("no data"));
    }
}
