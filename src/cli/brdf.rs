//! `gonio brdf …`: the material library on its own.
//!
//! `gonio brdf eval --model NAME --params JSON` reads one direction pair per stdin line,
//! `{"theta_l": .., "phi_l": .., "theta_v": .., "phi_v": ..}` (degrees, sample frame of
//! `conventions.md`: θ ∈ [0°, 90°), φ ∈ [0°, 360°)), and writes one line `{"rgb": [r, g, b]}`
//! (BRDF in 1/sr) per input line, in order. The first bad line stops the run with an error
//! naming its line number; nothing is evaluated before the model has been validated.

use anyhow::{anyhow, bail, Context, Result};
use gonio_devices::{Direction, Vec3};
use gonio_simulator::brdf::{list_models, BrdfModel, Rgb};
use serde::{Deserialize, Serialize};
use std::io::{BufRead, BufWriter, Write};
use std::process::ExitCode;

#[derive(clap::Subcommand, Debug)]
pub enum BrdfCommand {
    /// List the BRDF models and their parameters.
    List {
        #[arg(long)]
        json: bool,
    },
    /// Evaluate one model: direction pairs as JSON lines on stdin, `{"rgb": [r, g, b]}` (1/sr)
    /// per line on stdout.
    Eval {
        /// Model name (see `gonio brdf list`), e.g. `rough-conductor`.
        #[arg(long)]
        model: String,
        /// The model's parameters as a JSON object, e.g.
        /// `{"distribution": "ggx", "alpha": 0.1, "eta": [0.2, 0.9, 1.1], "k": [3.9, 2.4, 2.2]}`.
        #[arg(long, default_value = "{}")]
        params: String,
    },
}

pub fn run(cmd: BrdfCommand) -> Result<ExitCode> {
    match cmd {
        BrdfCommand::List { json } => {
            let models = list_models();
            if json {
                println!("{}", serde_json::to_string_pretty(&models)?);
            } else {
                for m in &models {
                    println!("{:<16} {}", m.name, m.summary);
                    for p in &m.params {
                        println!("    {:<22} {} ({})", p.name, p.description, p.range);
                    }
                }
            }
            Ok(ExitCode::SUCCESS)
        }
        BrdfCommand::Eval { model, params } => {
            let model = parse_model(&model, &params)?;
            let stdin = std::io::stdin().lock();
            let mut out = BufWriter::new(std::io::stdout().lock());
            eval_stream(&model, stdin, &mut out)?;
            out.flush().context("writing stdout")?;
            Ok(ExitCode::SUCCESS)
        }
    }
}

/// The parameters of `name` with their ranges, one per line, for error messages.
fn param_help(name: &str) -> String {
    list_models()
        .into_iter()
        .find(|m| m.name == name)
        .map(|m| {
            m.params
                .iter()
                .map(|p| format!("  {}: {} ({})", p.name, p.description, p.range))
                .collect::<Vec<_>>()
                .join("\n")
        })
        .unwrap_or_default()
}

/// Build and validate a model from its name and a JSON object of its parameters.
pub fn parse_model(name: &str, params: &str) -> Result<BrdfModel> {
    let names: Vec<&str> = list_models().iter().map(|m| m.name).collect();
    if !names.contains(&name) {
        bail!("unknown BRDF model `{name}`; valid models: {}", names.join(", "));
    }
    let value: serde_json::Value =
        serde_json::from_str(params).map_err(|e| anyhow!("model `{name}`: --params is not valid JSON: {e}"))?;
    let serde_json::Value::Object(mut obj) = value else {
        bail!("model `{name}`: --params must be a JSON object of parameters, got `{params}`");
    };
    match obj.get("model") {
        None => {}
        Some(serde_json::Value::String(m)) if m == name => {}
        Some(other) => bail!("model `{name}`: --params contains `model` = {other}, which contradicts --model"),
    }
    obj.insert("model".into(), serde_json::Value::String(name.into()));
    let model: BrdfModel = serde_json::from_value(serde_json::Value::Object(obj)).map_err(|e| {
        anyhow!(
            "model `{name}`: bad parameters: {e}\nparameters of `{name}`:\n{}",
            param_help(name)
        )
    })?;
    model.validate().map_err(|e| anyhow!("{e}"))?;
    Ok(model)
}

/// One input line.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct PairLine {
    theta_l: f64,
    phi_l: f64,
    theta_v: f64,
    phi_v: f64,
}

#[derive(Serialize)]
struct OutLine {
    rgb: Rgb,
}

fn direction(line: usize, which: &str, theta: f64, phi: f64) -> Result<Vec3> {
    if !(theta.is_finite() && (0.0..90.0).contains(&theta)) {
        bail!("line {line}: theta_{which} = {theta}: valid range is 0 ≤ θ < 90 (degrees)");
    }
    if !(phi.is_finite() && (0.0..360.0).contains(&phi)) {
        bail!("line {line}: phi_{which} = {phi}: valid range is 0 ≤ φ < 360 (degrees)");
    }
    Ok(Direction::from_degrees(theta, phi).vector())
}

/// Parse one input line (1-based `line` for messages) into unit (l, v).
fn parse_pair(text: &str, line: usize) -> Result<(Vec3, Vec3)> {
    let p: PairLine = serde_json::from_str(text).map_err(|e| {
        anyhow!(
            "line {line}: expected {{\"theta_l\": .., \"phi_l\": .., \"theta_v\": .., \"phi_v\": ..}} \
             (degrees): {e}"
        )
    })?;
    Ok((
        direction(line, "l", p.theta_l, p.phi_l)?,
        direction(line, "v", p.theta_v, p.phi_v)?,
    ))
}

/// Evaluate every line of `input`, writing one JSON line per input line; returns the count.
fn eval_stream<R: BufRead, W: Write>(model: &BrdfModel, input: R, out: &mut W) -> Result<usize> {
    let mut n = 0;
    for (i, text) in input.lines().enumerate() {
        let line = i + 1;
        let text = text.with_context(|| format!("reading stdin line {line}"))?;
        let (l, v) = parse_pair(&text, line)?;
        let rgb = model.eval(l, v);
        if !rgb.iter().all(|x| x.is_finite()) {
            bail!(
                "line {line}: model `{}` returned a non-finite value {rgb:?}",
                model.name()
            );
        }
        serde_json::to_writer(&mut *out, &OutLine { rgb }).context("writing stdout")?;
        out.write_all(b"\n").context("writing stdout")?;
        n += 1;
    }
    Ok(n)
}

#[cfg(test)]
mod tests {
    use super::*;

    const CONDUCTOR: &str = r#"{"distribution":"ggx","alpha":0.1,"eta":[0.2,0.9,1.1],"k":[3.9,2.4,2.2]}"#;

    fn err(r: Result<impl std::fmt::Debug>) -> String {
        format!("{:#}", r.expect_err("expected an error"))
    }

    #[test]
    fn parses_a_valid_model() {
        let m = parse_model("rough-conductor", CONDUCTOR).unwrap();
        assert_eq!(m.name(), "rough-conductor");
        let m = parse_model("lambert", r#"{"albedo":[0.5,0.5,0.5]}"#).unwrap();
        assert_eq!(
            m,
            BrdfModel::Lambert {
                albedo: [0.5, 0.5, 0.5]
            }
        );
        // A redundant but consistent `model` key is accepted.
        parse_model("lambert", r#"{"model":"lambert","albedo":[0.5,0.5,0.5]}"#).unwrap();
    }

    #[test]
    fn unknown_model_lists_the_valid_ones() {
        let e = err(parse_model("rough-conductr", CONDUCTOR));
        assert!(e.contains("unknown BRDF model `rough-conductr`"), "{e}");
        assert!(e.contains("rough-conductor") && e.contains("lambert"), "{e}");
    }

    #[test]
    fn unknown_parameter_is_named_with_the_valid_ones() {
        let e = err(parse_model("lambert", r#"{"albedo":[0.5,0.5,0.5],"roughness":0.1}"#));
        assert!(e.contains("model `lambert`") && e.contains("roughness"), "{e}");
        assert!(e.contains("albedo: diffuse albedo ([r, g, b], each 0..=1)"), "{e}");
    }

    #[test]
    fn missing_parameter_is_named() {
        let e = err(parse_model(
            "rough-conductor",
            r#"{"distribution":"ggx","alpha":0.1,"eta":[1,1,1]}"#,
        ));
        assert!(
            e.contains("model `rough-conductor`") && e.contains("missing field `k`"),
            "{e}"
        );
    }

    #[test]
    fn out_of_range_values_are_named_with_their_range() {
        let e = err(parse_model(
            "rough-conductor",
            r#"{"distribution":"ggx","alpha":-0.1,"eta":[1,1,1],"k":[1,1,1]}"#,
        ));
        assert!(e.contains("rough-conductor") && e.contains("`alpha` = -0.1"), "{e}");
        assert!(e.contains("valid range is 1e-4 ..= 1"), "{e}");
        let e = err(parse_model(
            "modified-phong",
            r#"{"kd":[0.8,0.8,0.8],"ks":[0.5,0.5,0.5],"exponent":10}"#,
        ));
        assert!(e.contains("modified-phong") && e.contains("kd + ks"), "{e}");
    }

    #[test]
    fn malformed_params_are_rejected() {
        let e = err(parse_model("lambert", "{albedo: 1"));
        assert!(e.contains("model `lambert`: --params is not valid JSON"), "{e}");
        let e = err(parse_model("lambert", "[0.5, 0.5, 0.5]"));
        assert!(e.contains("must be a JSON object"), "{e}");
        let e = err(parse_model("lambert", r#"{"model":"ward","albedo":[0.5,0.5,0.5]}"#));
        assert!(e.contains("contradicts --model"), "{e}");
        let e = err(parse_model(
            "rough-conductor",
            r#"{"distribution":"phong","alpha":0.1,"eta":[1,1,1],"k":[1,1,1]}"#,
        ));
        assert!(e.contains("phong") && e.contains("ggx"), "{e}");
    }

    #[test]
    fn pair_lines_follow_the_conventions() {
        let (l, v) = parse_pair(r#"{"theta_l":0,"phi_l":0,"theta_v":60,"phi_v":90}"#, 1).unwrap();
        assert!((l.z - 1.0).abs() < 1e-15);
        assert!(v.x.abs() < 1e-15 && (v.y - 60f64.to_radians().sin()).abs() < 1e-15);
        assert!((v.z - 0.5).abs() < 1e-15);
    }

    #[test]
    fn bad_pair_lines_name_the_line_and_field() {
        let e = err(parse_pair(r#"{"theta_l":10,"phi_l":0,"theta_v":95,"phi_v":0}"#, 7));
        assert!(
            e.contains("line 7") && e.contains("theta_v = 95") && e.contains("0 ≤ θ < 90"),
            "{e}"
        );
        let e = err(parse_pair(r#"{"theta_l":10,"phi_l":-5,"theta_v":5,"phi_v":0}"#, 3));
        assert!(
            e.contains("line 3") && e.contains("phi_l = -5") && e.contains("0 ≤ φ < 360"),
            "{e}"
        );
        let e = err(parse_pair(r#"{"theta_l":10,"phi_l":0,"theta_v":5}"#, 2));
        assert!(e.contains("line 2") && e.contains("missing field `phi_v`"), "{e}");
        let e = err(parse_pair(r#"{"theta_l":10,"phi_l":0,"theta_v":5,"phi_v":0,"x":1}"#, 2));
        assert!(e.contains("line 2") && e.contains("unknown field `x`"), "{e}");
        let e = err(parse_pair("10 0 5 0", 4));
        assert!(e.contains("line 4"), "{e}");
        let e = err(parse_pair("", 5));
        assert!(e.contains("line 5"), "{e}");
    }

    #[test]
    fn eval_stream_writes_one_line_per_input() {
        let m = parse_model("lambert", r#"{"albedo":[0.5,0.25,1.0]}"#).unwrap();
        let input = "{\"theta_l\":0,\"phi_l\":0,\"theta_v\":30,\"phi_v\":120}\n\
                     {\"theta_l\":89,\"phi_l\":359.5,\"theta_v\":45,\"phi_v\":0}\n";
        let mut out = Vec::new();
        assert_eq!(eval_stream(&m, input.as_bytes(), &mut out).unwrap(), 2);
        let text = String::from_utf8(out).unwrap();
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines.len(), 2);
        // Exact values: serde_json writes the shortest round-trip representation.
        let expect = [0.5, 0.25, 1.0].map(|a| a * std::f64::consts::FRAC_1_PI);
        let expect = format!("{{\"rgb\":{}}}", serde_json::to_string(&expect).unwrap());
        assert_eq!(lines, vec![expect.as_str(); 2]);
    }

    #[test]
    fn eval_stream_stops_at_the_first_bad_line() {
        let m = parse_model("rough-conductor", CONDUCTOR).unwrap();
        let input = "{\"theta_l\":10,\"phi_l\":0,\"theta_v\":10,\"phi_v\":180}\nnot json\n";
        let mut out = Vec::new();
        let e = err(eval_stream(&m, input.as_bytes(), &mut out));
        assert!(e.contains("line 2"), "{e}");
        // The good first line was answered (and is a strong specular peak).
        let first: serde_json::Value = serde_json::from_slice(out.split(|b| *b == b'\n').next().unwrap()).unwrap();
        assert!(first["rgb"][0].as_f64().unwrap() > 1.0, "{first}");
    }
}
