//! `pma bench --shares`: the share of samples that run the network per pass, per way of
//! leaving work out (`pma_model::bench::shares` counts). Prints the table and writes
//! `shares.json`.

use candle_core::Device;
use pma_model::bench::{PassShare, SharesReport, SharesRequest};
use pma_model::network::occupancy::OccupancyConfig;
use pma_model::train::Preset;

use super::super::progress::Phases;
use super::super::write_json;
use super::Args;

pub fn run(args: &Args, dev: &Device) -> anyhow::Result<()> {
    let preset: Preset = args.preset.parse()?;
    let scene = super::scene(args);
    let req = SharesRequest {
        preset,
        model: args.model.clone(),
        out: args.out.clone(),
        scene,
        train_steps: args.shares_steps,
        train_rays: args.shares_train_rays,
        threshold: args.shares_threshold,
        occupancy: OccupancyConfig::default(),
        occupancy_poses: args.occupancy_poses,
        eval_images: args.eval_images,
        batches: args.shares_batches,
        device: dev.clone(),
        numerics: super::super::numerics(),
    };
    let report = pma_model::bench::shares(&req, &mut Phases::new(args.quiet))?;
    print_tables(&report);
    let path = args.out.join("shares.json");
    write_json(&report, &path)?;
    println!("wrote {}", path.display());
    Ok(())
}

fn print_tables(r: &SharesReport) {
    println!(
        "\nshare of samples that ran the network, per pass: a count (deterministic for this \
         model and these rays), not a timing"
    );
    println!("preset {} | model {}", r.preset, r.model);
    if let Some(rays) = r.train_rays_per_step {
        println!(
            "  trained {} steps of {rays} rays",
            r.train_steps.unwrap_or(0)
        );
    }
    println!(
        "occupancy grid: {}; {:.1} % of cells occupied",
        r.grid,
        100.0 * r.grid_occupied_fraction
    );
    println!(
        "samples per ray: {} coarse + {} fine; w^p threshold {}",
        r.coarse_samples_per_ray, r.fine_samples_per_ray, r.threshold
    );
    if !r.render.is_empty() {
        println!(
            "\nrender: held-out views {:?} of the novel-view split, rays inside the body box",
            r.render_images
        );
        table(&r.render);
    }
    if !r.training_batches.is_empty() {
        println!(
            "\ntraining batches: {} batch(es) of {} rays from the preset's sampler, one forward \
             pass without gradients",
            r.batches, r.batch_rays
        );
        table(&r.training_batches);
    }
}

fn table(rows: &[PassShare]) {
    println!(
        "{:<32} {:>8} {:>9} {:>9} {:>9} {:>14}",
        "option", "rays", "coarse", "fine", "all", "empty skipped"
    );
    for s in rows {
        println!(
            "{:<32} {:>8} {:>8.1}% {:>8.1}% {:>8.1}% {:>14}",
            s.option,
            s.rays,
            100.0 * s.coarse(),
            100.0 * s.fine(),
            100.0 * s.all(),
            s.skipped_empty
        );
    }
}
