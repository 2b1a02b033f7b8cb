//! The shipped worlds load and have the character their files promise; bad files are located.

use worlds::World;
use worlds::spec::ObjectKind;

fn load(name: &str) -> World {
    World::load(worlds::worlds_dir().join(name)).unwrap_or_else(|e| panic!("{e}"))
}

#[test]
fn flat_yard_is_flat() {
    let w = load("flat_yard.toml");
    assert_eq!(w.terrain.height_range(), (0.0, 0.0));
    assert!(w.rocks.is_empty());
    assert_eq!(w.object("canister").unwrap().kind, ObjectKind::Canister);
}

#[test]
fn mars_yard_is_forty_metres_with_rocks_and_gentle_slopes() {
    let w = load("mars_yard.toml");
    assert_eq!(w.terrain.size(), [40.0, 40.0]);
    assert_eq!((w.terrain.nx, w.terrain.ny), (257, 257));
    assert!((50..2000).contains(&w.rocks.len()), "{} rocks", w.rocks.len());
    // Gentle: 95% of the ground under 12 degrees.
    let mut slopes: Vec<f64> = (0..w.terrain.ny)
        .step_by(4)
        .flat_map(|j| (0..w.terrain.nx).step_by(4).map(move |i| (i, j)))
        .map(|(i, j)| {
            let p = w.terrain.position(i, j);
            w.terrain.slope(p.x, p.y).to_degrees()
        })
        .collect();
    slopes.sort_by(f64::total_cmp);
    let p95 = slopes[slopes.len() * 95 / 100];
    assert!(p95 < 12.0 && p95 > 1.0, "95th percentile slope {p95} deg");
    // Start area is flat and free of rocks.
    assert!(w.terrain.slope(-12.0, -12.0).to_degrees() < 0.5);
    assert!(
        w.rocks.iter().all(|r| (r.position.coords.xy() - nalgebra::Vector2::new(-12.0, -12.0)).norm() > 3.0)
    );
    let c = w.object("canister").unwrap();
    assert!((c.position.z - w.ground_height(6.0, 5.0)).abs() < 1e-12);
    assert_eq!(w.objects.len(), 3);
}

#[test]
fn rough_field_has_slopes_near_the_limits() {
    let w = load("rough_field.toml");
    let max = (0..w.terrain.ny)
        .step_by(2)
        .flat_map(|j| (0..w.terrain.nx).step_by(2).map(move |i| (i, j)))
        .map(|(i, j)| {
            let p = w.terrain.position(i, j);
            w.terrain.slope(p.x, p.y).to_degrees()
        })
        .fold(0.0, f64::max);
    assert!(max > 25.0, "steepest {max} deg");
    let on_ramp = w.terrain.slope(0.0, -12.0).to_degrees();
    assert!((15.0..35.0).contains(&on_ramp), "ramp {on_ramp} deg");
}

#[test]
fn generation_is_deterministic_and_seeds_matter() {
    let a = load("mars_yard.toml");
    let b = load("mars_yard.toml");
    assert_eq!(a.terrain, b.terrain);
    assert_eq!(a.rocks, b.rocks);
    let c = World::load_with_seed(worlds::worlds_dir().join("mars_yard.toml"), 5).unwrap();
    assert_ne!(a.terrain, c.terrain);
    assert_ne!(a.rocks.len(), 0);
}

fn err(text: &str) -> String {
    World::from_str(text, "w.toml", std::path::Path::new("."), None).unwrap_err().to_string()
}

#[test]
fn malformed_worlds_name_file_line_and_key() {
    let e = err("name = \"x\"\n[terrain]\nsize_m = [-4.0, 10.0]\nresolution_m = 0.5\n");
    assert!(e.starts_with("w.toml:3:") && e.contains("terrain.size_m") && e.contains("positive"), "{e}");
    let e = err("name = \"x\"\n[terrain]\nsize_m = [4.0, 10.0]\nresolution_m = 0.5\nroughness = 2\n");
    assert!(e.starts_with("w.toml:5:") && e.contains("roughness"), "{e}");
    let e = err(
        "name = \"x\"\n[terrain]\nsize_m = [4.0, 10.0]\nresolution_m = 0.5\n[terrain.heightmap]\nimage = \"nope.png\"\nheight_range_m = [0.0, 1.0]\n",
    );
    assert!(e.starts_with("w.toml:6:") && e.contains("file not found") && e.contains("nope.png"), "{e}");
    let e = err(
        "name = \"x\"\n[terrain]\nsize_m = [4.0, 10.0]\nresolution_m = 0.5\n[[objects]]\nname = \"c\"\nkind = \"canister\"\nposition_m = [9.0, 0.0]\n",
    );
    assert!(e.starts_with("w.toml:8:") && e.contains("outside the terrain"), "{e}");
    let e = err(
        "name = \"x\"\n[terrain]\nsize_m = [4.0, 10.0]\nresolution_m = 0.5\n[[objects]]\nname = \"c\"\nkind = \"teapot\"\nposition_m = [1.0, 0.0]\n",
    );
    assert!(e.starts_with("w.toml:7:") && e.contains("teapot"), "{e}");
    let e = err(
        "name = \"x\"\n[terrain]\nsize_m = [4.0, 10.0]\nresolution_m = 0.5\n[rocks]\ncoverage_k = 0.9\nmin_diameter_m = 0.1\nmax_diameter_m = 0.5\n",
    );
    assert!(e.starts_with("w.toml:6:") && e.contains("rocks.coverage_k"), "{e}");
    let e = World::load("/no/such/world.toml").unwrap_err().to_string();
    assert!(e.starts_with("/no/such/world.toml: cannot read file"), "{e}");
}

#[test]
fn heightmap_images_set_the_heights() {
    let dir = tempfile::tempdir().unwrap();
    // 3 x 3 image: west column black, east column white; row 0 is north.
    let mut img = image::GrayImage::new(3, 3);
    for y in 0..3 {
        for x in 0..3 {
            img.put_pixel(x, y, image::Luma([(x * 127) as u8]));
        }
    }
    img.save(dir.path().join("h.png")).unwrap();
    let text = "name = \"hm\"\n[terrain]\nsize_m = [10.0, 10.0]\nresolution_m = 0.5\n[terrain.heightmap]\nimage = \"h.png\"\nheight_range_m = [1.0, 3.0]\n";
    std::fs::write(dir.path().join("w.toml"), text).unwrap();
    let w = World::load(dir.path().join("w.toml")).unwrap();
    assert!((w.ground_height(-5.0, 0.0) - 1.0).abs() < 1e-9);
    assert!((w.ground_height(5.0, 0.0) - (1.0 + 2.0 * 254.0 / 255.0)).abs() < 1e-3);
    assert!((w.ground_height(0.0, 3.0) - (1.0 + 127.0 / 255.0 * 2.0)).abs() < 1e-3);
}

#[test]
fn keep_clear_removes_exactly_the_rocks_that_reach_into_the_circle() {
    let mut w = World::load(worlds::worlds_dir().join("mars_yard.toml")).unwrap();
    // Right on a rock that the world file's keep-out zones know nothing of.
    let r = w.rocks.iter().max_by(|a, b| a.diameter.total_cmp(&b.diameter)).unwrap().clone();
    let (x, y, radius) = (r.position.x + 0.2, r.position.y - 0.1, 1.5);
    let reaches = |k: &worlds::Rock| (k.position.x - x).hypot(k.position.y - y) < radius + k.diameter / 2.0;
    let expected: Vec<_> = w.rocks.iter().filter(|k| !reaches(k)).cloned().collect();
    let removed = w.keep_clear(x, y, radius);
    assert!(removed >= 1, "the rock under the point is removed");
    assert_eq!(w.rocks, expected, "every other rock stays as it was");
    assert!(w.rocks.iter().all(|k| !reaches(k)));
}
