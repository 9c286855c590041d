//! `pto`: simulate the hydraulic PTO bench and check the paper's facts.
use pto_host::bench::Bench;
use pto_host::sim::SolverOptions;
fn main() {
    let b = Bench::reference();
    let all = pto_host::scenario::builtin();
    let filter = std::env::args().nth(1).unwrap_or_default();
    let sel: Vec<_> = all.into_iter().filter(|s| s.name.contains(&filter)).collect();
    let t0 = std::time::Instant::now();
    let out = pto_host::runner::run_all(&b, &sel, SolverOptions { rtol: std::env::var("RTOL").map(|v| v.parse().unwrap()).unwrap_or(1e-6), atol_scale: std::env::var("ATOL").map(|v| v.parse().unwrap()).unwrap_or(0.3) }, true);
    eprintln!("wall {:.2}", t0.elapsed().as_secs_f64());
    for o in &out { match &o.result { Ok(r) => println!("{:24} {:.3}s steps {} bal {:.1e}", o.scenario.name, r.stats.wall_s, r.stats.steps, r.balance.worst()), Err(e) => println!("{:24} ERR {e}", o.scenario.name) } }
    detail(&out);
    for f in pto_host::paper::check(&b, &out) { println!("{} {} | {}", if f.pass {"PASS"} else {"FAIL"}, f.id, f.measured); }
}
#[allow(dead_code)]
fn detail(out: &[pto_host::runner::Outcome]) {
    for o in out { if let Ok(r) = &o.result { println!("{} {:?} e {:.1e} p2 {:.1}..{:.1}", o.scenario.name, r.balance.volume_rel_error, r.balance.energy_rel_error, r.trace.p2.iter().cloned().fold(1e9,f64::min)/1e5, r.trace.p2.iter().cloned().fold(0.0,f64::max)/1e5);
      if o.scenario.name.starts_with("blocked") { for th in [20.0, 50.0, 75.0] { println!("   thr {th}: {:?}", pto_host::paper::autonomy(&r.trace, th)); } println!("   rpm0 {:.0}", r.trace.omega[1]*9.549); } } }
}
