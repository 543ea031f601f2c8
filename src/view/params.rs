//! Parsing of the viewer's parameters, shared by `gonio render` and the HTTP API so that a
//! URL state and a command line mean exactly the same scene.
//!
//! Every parser returns a [`ParamError`] naming the parameter, the value and what was
//! expected: the server answers it with a 400, the CLI prints it.

use super::render::Shape;

/// Largest rendered side (pixels). The page's canvases and `gonio render` share it.
pub const MAX_SIDE: usize = 2048;
/// Exposure range (a multiplier on the linear value before tone mapping).
pub const MAX_EXPOSURE: f64 = 1.0e6;

/// A parameter that could not be parsed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("parameter `{name}` = {value:?}: {expected}")]
pub struct ParamError {
    pub name: String,
    pub value: String,
    pub expected: String,
}

fn err(name: &str, value: &str, expected: impl Into<String>) -> ParamError {
    // Echo at most 64 characters of the offending value.
    let value: String = value.chars().take(64).collect();
    ParamError {
        name: name.to_string(),
        value,
        expected: expected.into(),
    }
}

fn finite(name: &str, s: &str) -> Result<f64, ParamError> {
    let x: f64 = s
        .trim()
        .parse()
        .map_err(|_| err(name, s, "expected a decimal number"))?;
    if !x.is_finite() {
        return Err(err(name, s, "expected a finite number"));
    }
    Ok(x)
}

/// A direction `θ,φ` in degrees: θ ∈ [0, 90), φ any finite angle (taken modulo 360).
pub fn direction(name: &str, s: &str) -> Result<[f64; 2], ParamError> {
    let (a, b) = s
        .split_once(',')
        .ok_or_else(|| err(name, s, "expected θ,φ in degrees, e.g. 30,45"))?;
    let th = finite(name, a)?;
    let ph = finite(name, b)?;
    if !(0.0..90.0).contains(&th) {
        return Err(err(name, s, "θ must be in [0, 90) degrees"));
    }
    if ph.abs() > 1.0e6 {
        return Err(err(name, s, "φ must be within ±1e6 degrees"));
    }
    Ok([th, ph.rem_euclid(360.0)])
}

/// An image size `WxH`, each side 1 ..= [`MAX_SIDE`].
pub fn size(name: &str, s: &str) -> Result<(usize, usize), ParamError> {
    let (a, b) = s
        .split_once(['x', 'X'])
        .ok_or_else(|| err(name, s, "expected WxH, e.g. 256x256"))?;
    let side = |t: &str| -> Result<usize, ParamError> {
        let v: usize = t
            .trim()
            .parse()
            .map_err(|_| err(name, s, "expected WxH with whole numbers"))?;
        if !(1..=MAX_SIDE).contains(&v) {
            return Err(err(name, s, format!("each side must be 1 ..= {MAX_SIDE}")));
        }
        Ok(v)
    };
    Ok((side(a)?, side(b)?))
}

/// A shape name.
pub fn shape(name: &str, s: &str) -> Result<Shape, ParamError> {
    match s {
        "plane" => Ok(Shape::Plane),
        "sphere" => Ok(Shape::Sphere),
        "cylinder" => Ok(Shape::Cylinder),
        _ => Err(err(name, s, "expected plane, sphere or cylinder")),
    }
}

/// An exposure multiplier: finite, > 0, ≤ [`MAX_EXPOSURE`].
pub fn exposure(name: &str, s: &str) -> Result<f64, ParamError> {
    let e = finite(name, s)?;
    if !(e > 0.0 && e <= MAX_EXPOSURE) {
        return Err(err(name, s, format!("expected a number in (0, {MAX_EXPOSURE}]")));
    }
    Ok(e)
}

/// A whole number in `0..bound` (an index: a texel coordinate, a light, a view).
pub fn index(name: &str, s: &str, bound: usize) -> Result<usize, ParamError> {
    let v: usize = s
        .trim()
        .parse()
        .map_err(|_| err(name, s, "expected a whole number ≥ 0"))?;
    if v >= bound {
        return Err(err(name, s, format!("must be below {bound}")));
    }
    Ok(v)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn directions_sizes_and_shapes() {
        assert_eq!(direction("light", "30,45").unwrap(), [30.0, 45.0]);
        assert_eq!(direction("light", "0,-90").unwrap(), [0.0, 270.0]);
        for bad in ["", "30", "NaN,0", "30,inf", "90,0", "-1,0", "a,b", "30,1e9"] {
            let e = direction("light", bad).unwrap_err();
            assert_eq!(e.name, "light", "{bad}");
        }
        assert_eq!(size("size", "64x32").unwrap(), (64, 32));
        for bad in ["0x1", "99999x1", "1x", "x", "64", "-1x3", "1e3x2"] {
            assert!(size("size", bad).is_err(), "{bad}");
        }
        assert!(shape("shape", "cube")
            .unwrap_err()
            .to_string()
            .contains("plane, sphere or cylinder"));
        assert!(exposure("exposure", "0").is_err());
        assert!(exposure("exposure", "NaN").is_err());
        assert_eq!(exposure("exposure", "2").unwrap(), 2.0);
        assert!(index("x", "5", 5).is_err());
        assert_eq!(index("x", "4", 5).unwrap(), 4);
    }
}
