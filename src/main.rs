//! The `gonio` command line. Each subcommand lives in `src/cli/`.

use clap::Parser;

/// Stop glibc's malloc from unmapping every freed image.
///
/// gonio allocates and frees a frame-sized buffer (0.8 MiB for a 256² RGB f32 image, 9 MiB
/// for a 1024 × 768 raw frame) thousands of times, on rayon's threads. glibc serves such
/// sizes with mmap and returns them with munmap (its threshold adapts upward only for
/// allocations of the thread that frees them), so every new image page-faults its memory in
/// again and every unmap stops both cores for a TLB shoot-down: `gonio sim btf` (6561
/// truth images of 256²) took 33.5 s on two cores, slower than the 27.4 s of one thread.
/// With buffers up to 32 MiB served from the heap it takes 11–14 s (measured with
/// `MALLOC_MMAP_THRESHOLD_`, which glibc reads first and which then still wins).
/// The trim threshold stays glibc's, so freed heap memory is still given back: keeping
/// 128 MiB of it as well bought no speed and made the soak campaign's acquisition hold
/// 90 MiB instead of 43 MiB, with a 12 MiB step after 200 s (`tests/campaigns/soak.sh`).
fn keep_freed_images_mapped() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    if std::env::var_os("MALLOC_MMAP_THRESHOLD_").is_none() {
        // SAFETY: mallopt only changes allocator parameters; called before any thread exists.
        unsafe {
            libc::mallopt(libc::M_MMAP_THRESHOLD, 32 << 20);
        }
    }
}

fn main() -> std::process::ExitCode {
    // Rust ignores SIGPIPE, so `println!` into a closed pipe (`gonio … --json | head`)
    // panics. Restore the default action: like every Unix filter, gonio then ends quietly
    // when its reader goes away. Nothing is lost by it: datasets are durable against any
    // kill (every stored measurement is fsynced before it is journalled), and progress
    // and logs go to stderr, so only a command's final report can meet a closed pipe.
    // SAFETY: called first thing in main, before any other thread exists.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
    keep_freed_images_mapped();
    let cli = gonio::cli::Cli::parse();
    gonio::cli::init_logging(cli.verbose, cli.quiet);
    match gonio::cli::run(cli) {
        Ok(code) => code,
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::ExitCode::from(1)
        }
    }
}
