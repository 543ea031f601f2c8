//! `gonio brdf …`: the material library on its own.

use anyhow::Result;
use std::process::ExitCode;

#[derive(clap::Subcommand, Debug)]
pub enum BrdfCommand {
    /// List the BRDF models and their parameters.
    List {
        #[arg(long)]
        json: bool,
    },
}

pub fn run(cmd: BrdfCommand) -> Result<ExitCode> {
    match cmd {
        BrdfCommand::List { json } => {
            let models = gonio_simulator::brdf::list_models();
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
    }
}
