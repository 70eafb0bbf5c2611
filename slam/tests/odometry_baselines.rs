//! The raw-odometry baselines of the vendored benchmark logs, reproduced by the crate's CARMEN
//! reader and relations metric.
//!
//! Expected numbers: `python3 slam_relations_eval.py --carmen-to-traj LOG /tmp/o.txt`, then
//! `python3 slam_relations_eval.py /tmp/o.txt RELATIONS --json /tmp/o.json` (and
//! `--formula cartographer`), run on 2026-12-01 with the team's reference script
//! (`shared/tools/slam_relations_eval.py`, outside this repository) on the uncompressed logs
//! that `testdata/slam/*.clf.gz` hold. The short (< 5 s) / long (> 60 s) rows come from the
//! script's `evaluate` on the relations filtered by |t2 − t1|.

mod common;

use common::load;
use scan3d_slam::carmen::CarmenLog;
use scan3d_slam::relations::{
    EvalOptions, EvalReport, Formula, MeanStd, Trajectory, evaluate, read_trajectory,
    write_trajectory,
};

/// The odometry trajectory as the script builds it: written with `write_trajectory` and read
/// back, so the text round trip is part of what is checked.
fn odometry_trajectory(log: &CarmenLog) -> Trajectory {
    let traj = Trajectory::from_scans(&log.scans, &log.odometry_poses());
    let mut text = Vec::new();
    write_trajectory(&traj, &mut text).unwrap();
    let back = read_trajectory(&text[..]).unwrap();
    assert_eq!(
        back, traj,
        "the log's 6-decimal values survive the text round trip"
    );
    back
}

#[track_caller]
fn assert_rel(what: &str, got: f64, want: f64) {
    let rel = ((got - want) / want).abs();
    assert!(rel < 1e-9, "{what}: {got} vs {want} (relative {rel:e})");
}

#[track_caller]
fn assert_mean_std(what: &str, got: MeanStd, want: (f64, f64)) {
    assert_rel(&format!("{what} mean"), got.mean, want.0);
    assert_rel(&format!("{what} std"), got.std, want.1);
}

#[test]
fn intel_raw_odometry_reproduces_the_scripts_baseline() {
    let (log, relations) = load("intel");
    assert_eq!((log.scans.len(), log.odometry.len()), (13_631, 26_915));
    assert_eq!(log.scans[0].timestamp.text, "976052857.337530");
    assert_eq!(log.largest_reading(), Some(81.83));
    let traj = odometry_trajectory(&log);
    let r: EvalReport = evaluate(&traj, &relations, &EvalOptions::default());
    assert_eq!(
        (
            r.relations,
            r.matched_within_1ms,
            r.matched_within_10us,
            r.all.used
        ),
        (2984, 2984, 2984, 2984)
    );
    assert_eq!(r.max_dt_used_s, 0.0);
    assert_mean_std(
        "abs trans",
        r.all.abs_trans_m,
        (7.370237817484781, 14.34912117180661),
    );
    assert_mean_std(
        "sq trans",
        r.all.sq_trans_m2,
        (260.2176838894716, 781.2997566978355),
    );
    assert_mean_std(
        "abs rot",
        r.all.abs_rot_deg,
        (39.166302116513364, 53.79055219060474),
    );
    assert_mean_std(
        "sq rot",
        r.all.sq_rot_deg2,
        (4427.422726452179, 7488.842104785972),
    );
    assert_rel("max trans", r.all.max_trans_m, 70.02153821364291);
    assert_rel("max rot", r.all.max_rot_deg, 179.75005596192108);
    assert_rel("eps", r.all.kummerle_eps, 261.56635397670817);
    assert_eq!((r.short.used, r.long.used), (1732, 1210));
    assert_mean_std(
        "short trans",
        r.short.abs_trans_m,
        (0.021977098213571553, 0.019877265972995044),
    );
    assert_mean_std(
        "short rot",
        r.short.abs_rot_deg,
        (1.4595766909296746, 1.1845416523207075),
    );
    assert_mean_std(
        "long trans",
        r.long.abs_trans_m,
        (18.139837240102068, 17.682449804372723),
    );
    assert_mean_std(
        "long rot",
        r.long.abs_rot_deg,
        (94.35388910915302, 44.82449178865524),
    );

    let carto = EvalOptions {
        formula: Formula::Cartographer,
        ..EvalOptions::default()
    };
    let r = evaluate(&traj, &relations, &carto);
    assert_mean_std(
        "carto trans",
        r.all.abs_trans_m,
        (7.372978064630855, 14.456297730769071),
    );
    assert_mean_std(
        "carto sq trans",
        r.all.sq_trans_m2,
        (263.3453496221668, 796.250183471422),
    );
}

#[test]
fn aces_raw_odometry_reproduces_the_scripts_baseline() {
    let (log, relations) = load("aces");
    assert_eq!((log.scans.len(), log.odometry.len()), (7_374, 7_375));
    assert_eq!(log.largest_reading(), Some(50.0));
    let traj = odometry_trajectory(&log);
    let r = evaluate(&traj, &relations, &EvalOptions::default());
    assert_eq!(
        (
            r.relations,
            r.matched_within_1ms,
            r.matched_within_10us,
            r.all.used
        ),
        (1279, 1279, 1279, 1279)
    );
    assert_mean_std(
        "abs trans",
        r.all.abs_trans_m,
        (0.5493095146398761, 2.6744455801340656),
    );
    assert_mean_std(
        "sq trans",
        r.all.sq_trans_m2,
        (7.454400103972538, 45.683506135759266),
    );
    assert_mean_std(
        "abs rot",
        r.all.abs_rot_deg,
        (2.3275413642587597, 6.503434641057502),
    );
    assert_mean_std(
        "sq rot",
        r.all.sq_rot_deg2,
        (47.71211093284223, 240.06118305108234),
    );
    assert_rel("max trans", r.all.max_trans_m, 18.899080838858726);
    assert_rel("max rot", r.all.max_rot_deg, 46.04540943101149);
    assert_rel("eps", r.all.kummerle_eps, 7.4689340440974785);
    assert_eq!((r.short.used, r.long.used), (1168, 88));
    assert_mean_std(
        "short trans",
        r.short.abs_trans_m,
        (0.03734135968466703, 0.039910077699497136),
    );
    assert_mean_std(
        "long trans",
        r.long.abs_trans_m,
        (7.473823567645991, 7.241801864534256),
    );

    let carto = EvalOptions {
        formula: Formula::Cartographer,
        ..EvalOptions::default()
    };
    let r = evaluate(&traj, &relations, &carto);
    assert_mean_std(
        "carto trans",
        r.all.abs_trans_m,
        (0.5635764230205718, 2.7236548055566914),
    );
}
