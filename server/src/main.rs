//! `fedvla`: a thin dispatcher; each subcommand lives in its own module under src/cmd/.

mod cmd;

use clap::Parser;

#[derive(Parser)]
#[command(name = "fedvla", version, about = "Federated learning of the SmolVLA robot policy")]
struct Cli {
    #[command(subcommand)]
    command: cmd::Command,
}

fn main() -> anyhow::Result<()> {
    limit_malloc_arenas();
    cmd::run(Cli::parse().command)
}

/// How many arenas glibc's malloc may make, unless `MALLOC_ARENA_MAX` says otherwise. The server makes its large
/// allocations (decoded updates, the aggregate, models and their bytes) on tokio's worker and blocking threads,
/// and by default glibc gives each such thread an arena of its own, up to eight a core, each keeping the pages of
/// what was freed in it: a round's memory then grew with the number of clients it took, though the aggregation
/// holds one update at a time (server/tests/aggregation_memory.rs, `small`: +11 models over a round of 5 clients,
/// +19 over one of 20; with 2 arenas, +7 to +10 over either, and 4 arenas still grew by 2 to 4 models at 20).
#[cfg(all(target_os = "linux", target_env = "gnu"))]
const MALLOC_ARENAS: i32 = 2;

#[cfg(all(target_os = "linux", target_env = "gnu"))]
#[allow(unsafe_code)]
fn limit_malloc_arenas() {
    if std::env::var_os("MALLOC_ARENA_MAX").is_none() {
        // SAFETY: mallopt only sets a tuning parameter of the allocator, here before any other thread exists.
        unsafe {
            libc::mallopt(libc::M_ARENA_MAX, MALLOC_ARENAS);
        }
    }
}

#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
fn limit_malloc_arenas() {}
