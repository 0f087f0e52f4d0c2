//! `pma demo` (placeholder until its issue lands; replaced by the owner of this subcommand).

#[derive(clap::Args)]
pub struct Args {}

pub fn run(_args: Args) -> anyhow::Result<()> {
    anyhow::bail!("`pma demo` is not implemented yet")
}
