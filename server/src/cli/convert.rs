//! `scan3d convert A B`: maps between `.bt` and `.ot` (as OctoMap's `convert_octree`), and
//! clouds from `.graph`/`.scans`/`.ply`/`.pcd` to `.scans`/`.ply`/`.pcd` (sensor origins kept).

use std::io::Write;
use std::path::PathBuf;

use super::map::{TreeFormat, load_cloud, read_tree, report_dropped, write_tree};
use scan3d_map::cloud::io::{self, CloudFormat};

/// Options of `scan3d convert`.
#[derive(Debug, clap::Args)]
pub struct ConvertArgs {
    /// The input: a map (`.bt`, `.ot`) or a cloud (`.graph`, `.scans`, `.ply`, `.pcd`).
    pub input: PathBuf,
    /// The output, of the same kind (format from the extension).
    pub output: PathBuf,
    /// Sensor origin `x,y,z` for a PLY/PCD cloud that carries none.
    #[arg(long, value_parser = super::map::parse_xyz_arg, allow_negative_numbers = true)]
    pub origin: Option<[f64; 3]>,
}

/// Runs `scan3d convert`.
pub fn run(args: &ConvertArgs, out: &mut dyn Write) -> anyhow::Result<()> {
    match (TreeFormat::of(&args.input), TreeFormat::of(&args.output)) {
        (Some(_), Some(_)) => {
            let tree = read_tree(&args.input)?;
            write_tree(&args.output, &tree)?;
            writeln!(
                out,
                "wrote {} ({} nodes, {} leaves)",
                args.output.display(),
                tree.num_nodes(),
                tree.num_leaves()
            )?;
            return Ok(());
        }
        (Some(_), None) | (None, Some(_)) => anyhow::bail!(
            "cannot convert between a map and a cloud ({} → {})",
            args.input.display(),
            args.output.display()
        ),
        (None, None) => {}
    }
    if CloudFormat::from_path(&args.output).is_none() {
        anyhow::bail!(
            "{}: unknown output format (maps: .bt .ot; clouds: .scans .ply .pcd)",
            args.output.display()
        );
    }
    let cloud = load_cloud(&args.input, args.origin)?;
    report_dropped(&cloud, out)?;
    let scans = cloud.bundles;
    io::save(&args.output, &scans)?;
    let points: usize = scans.iter().map(|s| s.points.len()).sum();
    writeln!(
        out,
        "wrote {} ({} scans, {points} points)",
        args.output.display(),
        scans.len()
    )?;
    Ok(())
}
