//! `scan3d map INPUT --resolution R … --out OUT.bt|OUT.ot`: a point cloud (OctoMap `.graph`, `.scans`,
//! PLY or PCD) filtered as asked and inserted into an OctoMap-identical occupancy octree; or a
//! recorded session directory, streamed through the server pipeline (assembly by eq. 1, the
//! filters per revolution, insertion per half revolution), which gives the same map as
//! assembling the session to `.scans` and mapping that, without holding the session.
//!
//! Each scan is inserted from its own sensor origin with OctoMap's `insertPointCloud`
//! semantics (`--max-range` cuts rays, `--hit/--miss/--clamp` set the sensor model), so the
//! `.bt`/`.ot` written equal what OctoMap writes for the same input, byte for byte.

use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::Context;
use indicatif::{ProgressBar, ProgressStyle};

use crate::pipeline::PipelineSettings;
use crate::pipeline::offline::{MAP_ONLY, run_session as run_session_pipeline};
use scan3d_map::cloud::RayBundle;
use scan3d_map::cloud::filter::{Filter, apply_all};
use scan3d_map::cloud::io::{self, LoadedBundles};
use scan3d_map::octree::{
    InsertStats, Octree, Resolution, SensorModel, VoxelMap, read_graph_from, visit_graph,
};

/// A point `x,y,z` on the command line (clap value parser).
pub fn parse_xyz_arg(text: &str) -> Result<[f64; 3], String> {
    super::parse_finite_numbers(text, "x,y,z")
}

/// Two probabilities `MIN,MAX` on the command line.
fn parse_clamp(text: &str) -> Result<(f64, f64), String> {
    let (lo, hi) = text
        .split_once(',')
        .ok_or_else(|| format!("expected MIN,MAX, got {text:?}"))?;
    let parse = |v: &str| {
        v.trim()
            .parse::<f64>()
            .ok()
            .filter(|p| *p > 0.0 && *p < 1.0)
            .ok_or_else(|| format!("{v:?} is not a probability in (0, 1)"))
    };
    let (lo, hi) = (parse(lo)?, parse(hi)?);
    if lo >= hi {
        return Err(format!("clamp minimum {lo} must be below the maximum {hi}"));
    }
    Ok((lo, hi))
}

/// A probability in (0, 1) on the command line.
fn parse_probability(text: &str) -> Result<f64, String> {
    text.trim()
        .parse::<f64>()
        .ok()
        .filter(|p| *p > 0.0 && *p < 1.0)
        .ok_or_else(|| format!("{text:?} is not a probability in (0, 1)"))
}

/// Options of `scan3d map`.
#[derive(Debug, clap::Args)]
pub struct MapArgs {
    /// The cloud: `.graph` (OctoMap ScanGraph), `.scans`, `.ply` or `.pcd`; or a session
    /// directory (`data_dir/sessions/<edge>/<session-id>`).
    pub input: PathBuf,
    /// Voxel edge length, metres.
    #[arg(long, alias = "res", value_name = "M")]
    pub resolution: f64,
    /// Rays longer than this are cut (free up to the cut, no hit); negative = no limit.
    #[arg(long, value_name = "M", default_value_t = -1.0, allow_negative_numbers = true)]
    pub max_range: f64,
    /// Sensor origin `x,y,z` for a PLY/PCD cloud that carries none.
    #[arg(long, value_parser = parse_xyz_arg, allow_negative_numbers = true)]
    pub origin: Option<[f64; 3]>,
    /// Hit probability (OctoMap default 0.7).
    #[arg(long, default_value_t = 0.7, value_parser = parse_probability)]
    pub hit: f64,
    /// Miss probability (OctoMap default 0.4).
    #[arg(long, default_value_t = 0.4, value_parser = parse_probability)]
    pub miss: f64,
    /// Clamping probabilities `MIN,MAX` (OctoMap default 0.1192,0.971).
    #[arg(long, value_parser = parse_clamp)]
    pub clamp: Option<(f64, f64)>,
    /// Point-cloud filters, applied in the order given: `voxel:LEAF`,
    /// `box:x0,y0,z0,x1,y1,z1`, `box-out:…`, `sor:K,ALPHA`, `gauss:SIGMA,RADIUS`.
    #[arg(long = "filter", value_name = "FILTER", allow_hyphen_values = true)]
    pub filters: Vec<Filter>,
    /// The map to write: `.bt` (max-likelihood, as OctoMap's writeBinary) or `.ot` (full).
    #[arg(long)]
    pub out: PathBuf,
    /// No progress bar.
    #[arg(long)]
    pub quiet: bool,
    /// For a session directory: go on with the readable rest of a damaged recording (with a
    /// warning) instead of failing.
    #[arg(long)]
    pub lenient: bool,
}

impl MapArgs {
    /// The sensor model these options give.
    pub fn model(&self) -> SensorModel {
        let (lo, hi) = self.clamp.unwrap_or((0.1192, 0.971));
        SensorModel::from_probabilities(self.hit, self.miss, lo, hi, 0.5)
    }
}

/// Loads any cloud the CLI accepts, with sensor origins: `.graph` through OctoMap's pose
/// transform, `.scans`/`.ply`/`.pcd` through [`scan3d_map::cloud::io`], with the count of points
/// the reader dropped for non-finite values.
pub fn load_cloud(path: &Path, origin: Option<[f64; 3]>) -> anyhow::Result<LoadedBundles> {
    if is_graph(path) {
        // Streamed: a large `.graph` is never in memory whole, only the bundles it holds.
        let file =
            std::fs::File::open(path).with_context(|| format!("cannot read {}", path.display()))?;
        let scans = read_graph_from(std::io::BufReader::with_capacity(1 << 16, file))
            .with_context(|| format!("{}", path.display()))?;
        Ok(LoadedBundles {
            bundles: scans,
            dropped_nonfinite: 0,
        })
    } else {
        Ok(io::load_counted(path, origin)?)
    }
}

/// Whether `path` names an OctoMap ScanGraph (`.graph`).
fn is_graph(path: &Path) -> bool {
    path.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| e.eq_ignore_ascii_case("graph"))
}

/// `scan3d map GRAPH` without filters: each node inserted as it is read, so only the map and
/// one node are ever in memory (no cloud to hold, page in and free). Returns the map, its
/// totals, and the nodes and points read.
fn map_graph_streaming(args: &MapArgs) -> anyhow::Result<(VoxelMap, InsertStats, usize, usize)> {
    let path = &args.input;
    let file =
        std::fs::File::open(path).with_context(|| format!("cannot read {}", path.display()))?;
    let len = file.metadata().map_or(0, |m| m.len());
    let bar = (!args.quiet && len > 16 << 20).then(|| {
        let bar = ProgressBar::new(len);
        bar.set_style(
            ProgressStyle::with_template(
                "{msg} [{bar:40}] {binary_bytes}/{binary_total_bytes} {eta}",
            )
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
        );
        bar.set_message("inserting");
        bar
    });
    let source = std::io::BufReader::with_capacity(1 << 16, file);
    let mut map = VoxelMap::new(Resolution::new(args.resolution)?, args.model());
    let mut points = 0;
    // The file is read and parsed on a thread of its own while the previous node is
    // inserted; two buffers go back and forth, so memory stays two nodes.
    let (full_tx, full_rx) = std::sync::mpsc::sync_channel::<RayBundle>(1);
    let (empty_tx, empty_rx) = std::sync::mpsc::channel::<RayBundle>();
    let reader_bar = bar.clone();
    let reader = std::thread::spawn(move || {
        let mut send = |bundle: &mut RayBundle| {
            // The parsed node goes over whole; the reader goes on in a returned buffer.
            let spare = empty_rx.try_recv().unwrap_or_default();
            let full = std::mem::replace(bundle, spare);
            // A closed channel means the inserting side has stopped: nothing left to do.
            let _ = full_tx.send(full);
        };
        match reader_bar {
            Some(bar) => visit_graph(bar.wrap_read(source), &mut send),
            None => visit_graph(source, &mut send),
        }
    });
    for bundle in full_rx {
        points += bundle.points.len();
        map.insert_bundle(&bundle, args.max_range);
        let _ = empty_tx.send(bundle);
    }
    let nodes = reader
        .join()
        .unwrap_or_else(|panic| std::panic::resume_unwind(panic))
        .with_context(|| format!("{}", path.display()))?;
    if let Some(bar) = bar {
        bar.finish_and_clear();
    }
    let stats = map.totals();
    Ok((map, stats, nodes, points))
}

/// Prints the reader's count of dropped non-finite points, if any.
pub fn report_dropped(loaded: &LoadedBundles, out: &mut dyn Write) -> std::io::Result<()> {
    if loaded.dropped_nonfinite > 0 {
        writeln!(
            out,
            "dropped {} points with NaN or infinite coordinates or origins while reading",
            loaded.dropped_nonfinite
        )?;
    }
    Ok(())
}

/// Which octree format a path names.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TreeFormat {
    /// `.bt`: OctoMap's binary max-likelihood format.
    Bt,
    /// `.ot`: OctoMap's full format with log-odds.
    Ot,
}

impl TreeFormat {
    /// The format named by `path`'s extension.
    pub fn of(path: &Path) -> Option<Self> {
        match path.extension()?.to_str()?.to_ascii_lowercase().as_str() {
            "bt" => Some(Self::Bt),
            "ot" => Some(Self::Ot),
            _ => None,
        }
    }
}

/// Reads a `.bt` or `.ot` file with OctoMap's default sensor model.
pub fn read_tree(path: &Path) -> anyhow::Result<Octree> {
    if TreeFormat::of(path).is_none() {
        anyhow::bail!("{}: not a map (expected .bt or .ot)", path.display());
    }
    let bytes = std::fs::read(path).with_context(|| format!("cannot read {}", path.display()))?;
    Octree::read(&bytes, SensorModel::default()).with_context(|| format!("{}", path.display()))
}

/// Writes `tree` as `.bt` or `.ot`, as the extension says.
pub fn write_tree(path: &Path, tree: &Octree) -> anyhow::Result<()> {
    let bytes = match TreeFormat::of(path) {
        Some(TreeFormat::Bt) => tree.to_bt_bytes(),
        Some(TreeFormat::Ot) => tree.to_ot_bytes(),
        None => anyhow::bail!("{}: a map must end in .bt or .ot", path.display()),
    };
    std::fs::write(path, bytes).with_context(|| format!("cannot write {}", path.display()))
}

/// Inserts every scan, with a progress bar over points when `progress` is set.
pub fn build_map(
    scans: &[RayBundle],
    res: f64,
    max_range: f64,
    model: SensorModel,
    progress: bool,
) -> anyhow::Result<(VoxelMap, InsertStats)> {
    let mut map = VoxelMap::new(Resolution::new(res)?, model);
    let total: u64 = scans.iter().map(|s| s.points.len() as u64).sum();
    let bar = if progress && total > 1_000_000 {
        let bar = ProgressBar::new(total);
        bar.set_style(
            ProgressStyle::with_template("{msg} [{bar:40}] {human_pos}/{human_len} points {eta}")
                .unwrap_or_else(|_| ProgressStyle::default_bar()),
        );
        bar.set_message("inserting");
        Some(bar)
    } else {
        None
    };
    for scan in scans {
        map.insert_bundle(scan, max_range);
        if let Some(bar) = &bar {
            bar.inc(scan.points.len() as u64);
        }
    }
    if let Some(bar) = bar {
        bar.finish_and_clear();
    }
    let stats = map.totals();
    Ok((map, stats))
}

/// Runs `scan3d map`.
pub fn run(args: &MapArgs, out: &mut dyn Write) -> anyhow::Result<()> {
    if TreeFormat::of(&args.out).is_none() {
        anyhow::bail!("{}: a map must end in .bt or .ot", args.out.display());
    }
    Resolution::new(args.resolution)?;
    if args.input.is_dir() {
        return run_session(args, out);
    }
    if is_graph(&args.input) && args.filters.is_empty() {
        let (map, stats, nodes, points) = map_graph_streaming(args)?;
        writeln!(
            out,
            "{}: {nodes} scans, {points} points",
            args.input.display()
        )?;
        let written = write_map(args, &map, &stats, out);
        std::thread::spawn(move || drop(map));
        return written;
    }
    let cloud = load_cloud(&args.input, args.origin)?;
    let loaded: usize = cloud.bundles.iter().map(|s| s.points.len()).sum();
    writeln!(
        out,
        "{}: {} scans, {loaded} points",
        args.input.display(),
        cloud.bundles.len()
    )?;
    report_dropped(&cloud, out)?;
    let mut scans = cloud.bundles;
    if !args.filters.is_empty() {
        scans = apply_all(&args.filters, scans)?;
        let kept: usize = scans.iter().map(|s| s.points.len()).sum();
        let names: Vec<String> = args.filters.iter().map(ToString::to_string).collect();
        writeln!(out, "filters {}: {kept} points kept", names.join(" → "))?;
    }
    let (map, stats) = build_map(
        &scans,
        args.resolution,
        args.max_range,
        args.model(),
        !args.quiet,
    )?;
    let written = write_map(args, &map, &stats, out);
    // Freeing the map and the cloud (tens of thousands of allocations at fine resolutions) is
    // left to a thread of its own: a one-shot `scan3d map` exits without waiting for it, and
    // a long-lived caller (the tests) still gets the memory back.
    std::thread::spawn(move || drop((map, scans)));
    written
}

/// The pipeline settings `scan3d map SESSION_DIR` maps with: the per-revolution filters are
/// the voxel grid and the pass-through boxes; SOR and Gaussian need the whole cloud, which a
/// streaming map never holds, so they are refused (assemble to `.scans` and map that instead).
pub fn session_settings(args: &MapArgs) -> anyhow::Result<PipelineSettings> {
    if let Some(f) = args
        .filters
        .iter()
        .find(|f| matches!(f, Filter::Sor { .. } | Filter::Gauss { .. }))
    {
        anyhow::bail!(
            "--filter {f}: a session is mapped revolution by revolution, and this filter needs              the whole cloud (use `scan3d assemble … --out cloud.scans`, then map the cloud)"
        );
    }
    if args.origin.is_some() {
        anyhow::bail!("--origin is for PLY/PCD clouds; a session carries its sensor origins");
    }
    Ok(PipelineSettings {
        resolution_m: args.resolution,
        max_range_m: (args.max_range >= 0.0).then_some(args.max_range),
        sensor: args.model(),
        revolution_filters: args.filters.clone(),
        ..PipelineSettings::default()
    })
}

/// `scan3d map SESSION_DIR`: the session streamed through the pipeline's assembly, filters and
/// octree stages (memory bounded by the map).
fn run_session(args: &MapArgs, out: &mut dyn Write) -> anyhow::Result<()> {
    let settings = session_settings(args)?;
    if args.max_range == 0.0 {
        anyhow::bail!("--max-range 0 would cut every ray (use a negative value for no limit)");
    }
    let (pipeline, _report) = run_session_pipeline(&args.input, &settings, MAP_ONLY, args.lenient)
        .with_context(|| {
            format!(
                "cannot map the session {} (--lenient maps what is readable)",
                args.input.display()
            )
        })?;
    let mut pipeline = pipeline;
    let status = pipeline.status();
    writeln!(
        out,
        "{}: {} frames, {} static scans at {} positions, {} points",
        args.input.display(),
        status.frames,
        pipeline.assembly().static_scans(),
        status.positions.len(),
        status.points
    )?;
    if status.missing_frames + status.undecodable_frames + status.orphan_samples > 0 {
        writeln!(
            out,
            "skipped: {} frames missing from the session, {} undecodable frames, {} static-scan \
             samples without their scan",
            status.missing_frames, status.undecodable_frames, status.orphan_samples
        )?;
    }
    if !args.filters.is_empty() {
        let names: Vec<String> = args.filters.iter().map(ToString::to_string).collect();
        writeln!(
            out,
            "filters {} per revolution: {} points kept",
            names.join(" → "),
            status.points
        )?;
    }
    let map = pipeline.maps().session_map();
    write_map(args, map, &map.totals(), out)
}

/// Prints what the insertion skipped and writes the map.
fn write_map(
    args: &MapArgs,
    map: &VoxelMap,
    stats: &InsertStats,
    out: &mut dyn Write,
) -> anyhow::Result<()> {
    if stats.skipped_nonfinite > 0 {
        writeln!(
            out,
            "skipped {} points with NaN or infinite coordinates",
            stats.skipped_nonfinite
        )?;
    }
    if stats.degenerate_rays > 0 {
        writeln!(
            out,
            "skipped {} rays of zero or infinite f32 length (their endpoints still count as hits)",
            stats.degenerate_rays
        )?;
    }
    if stats.out_of_bounds > 0 {
        writeln!(
            out,
            "dropped {} rays leaving the octree's key range",
            stats.out_of_bounds
        )?;
    }
    let tree = map.to_octree();
    write_tree(&args.out, &tree)?;
    writeln!(
        out,
        "wrote {}: resolution {} m, {} nodes, {} leaves ({} occupied, {} free)",
        args.out.display(),
        args.resolution,
        tree.num_nodes(),
        tree.num_leaves(),
        tree.num_occupied(),
        tree.num_free()
    )?;
    Ok(())
}
