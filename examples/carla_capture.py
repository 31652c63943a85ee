#!/usr/bin/env python
"""Capture cubemaps in a running CARLA server, in the layout ``omniscape-torch convert`` reads.

Needs a CARLA server and its Python API (``import carla``, the wheel or egg matching the
server's version); not run by the tests. Spawns a vehicle on autopilot and, attached to it at
one point, six 90-degree cameras of each kind (RGB, depth, semantic segmentation, and instance
segmentation where the server has it: CARLA 0.9.14 and later) at the rig rotations of
``DESIGN.md`` (``carla.Rotation(pitch, yaw, roll)``, degrees):

    front (0, 0, 0)   back yaw 180   left yaw -90   right yaw +90   up pitch +90   down pitch -90

The world runs in synchronous mode (fixed time step), so the 18 (or 24) images of a tick are
of one instant. Every ``--every`` ticks it writes::

    OUT/<frame:08d>/{front,back,left,right,up,down}_{rgb,depth,labels,instances}.png
    OUT/<frame:08d>/vehicle.json    pose (CARLA's frame, metres, degrees), velocity, time

depth, labels and instances saved with CARLA's ``Raw`` converter (24-bit depth in R, G, B; tag
in R; the instance camera's object id in G and B, ``convert`` writes instance ids and boxes
from it).
Then::

    omniscape-torch convert --cubemaps OUT --out OMNI --label-set new   # CARLA >= 0.9.14
    (--label-set 23 for CARLA 0.9.10 to 0.9.13, 13 for 0.9.0 to 0.9.9)

Example:
    python examples/carla_capture.py --host localhost --town Town01 --frames 100 --out caps
"""

from __future__ import annotations

import argparse
import json
import os
import queue
import random
import sys
from pathlib import Path

try:
    import carla
except ImportError:  # pragma: no cover - only on machines with the CARLA Python API
    carla = None

#: Face name -> (pitch, yaw, roll) in degrees, CARLA's rotation convention (DESIGN.md table).
RIG = {
    "front": (0.0, 0.0, 0.0),
    "back": (0.0, 180.0, 0.0),
    "left": (0.0, -90.0, 0.0),
    "right": (0.0, 90.0, 0.0),
    "up": (90.0, 0.0, 0.0),
    "down": (-90.0, 0.0, 0.0),
}
FACES = ("front", "back", "left", "right", "up", "down")
#: Modality -> CARLA blueprint.
SENSORS = {
    "rgb": "sensor.camera.rgb",
    "depth": "sensor.camera.depth",
    "labels": "sensor.camera.semantic_segmentation",
    "instances": "sensor.camera.instance_segmentation",   # CARLA >= 0.9.14: skipped before
}


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--host", default="localhost")
    p.add_argument("--port", type=int, default=2000)
    p.add_argument("--tm-port", type=int, default=8000, help="traffic manager port")
    p.add_argument("--town", default=None, help="map to load (default: the current one)")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--face-size", type=int, default=1024, help="pixels per face side")
    p.add_argument("--frames", type=int, default=100, help="captures to write")
    p.add_argument("--every", type=int, default=10, help="ticks between captures")
    p.add_argument("--warmup", type=int, default=20, help="ticks before the first capture")
    p.add_argument("--delta", type=float, default=0.05, help="fixed time step, seconds")
    p.add_argument("--height", type=float, default=2.0,
                   help="rig height above the vehicle origin, metres")
    p.add_argument("--x", type=float, default=0.0, help="rig offset forward, metres")
    p.add_argument("--vehicle", default="vehicle.*", help="blueprint filter of the vehicle")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--timeout", type=float, default=20.0, help="seconds to wait for a sensor")
    return p.parse_args(argv)


def _atomic_json(path: Path, data: dict) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(data, indent=2) + "\n")
    os.replace(tmp, path)


def _save(image, path: Path, converter) -> None:
    """Save through a temporary name then rename, so a capture never holds half a file."""
    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
    image.save_to_disk(str(tmp), converter)
    os.replace(tmp, path)


def spawn_rig(world, vehicle, face_size: int, height: float, x: float) -> dict:
    """Spawn the 18 cameras (24 with instance segmentation); returns ``{(face, modality):
    (sensor, queue)}``."""
    library = world.get_blueprint_library()
    rig = {}
    for modality, name in SENSORS.items():
        if not library.filter(name):   # a server without this sensor (instances before 0.9.14)
            continue
        bp = library.find(name)
        bp.set_attribute("image_size_x", str(face_size))
        bp.set_attribute("image_size_y", str(face_size))
        bp.set_attribute("fov", "90")
        if bp.has_attribute("sensor_tick"):
            bp.set_attribute("sensor_tick", "0.0")   # every tick
        if modality == "rgb":
            for attr, value in (("motion_blur_intensity", "0"), ("enable_postprocess_effects",
                                                                  "True")):
                if bp.has_attribute(attr):
                    bp.set_attribute(attr, value)
        for face in FACES:
            pitch, yaw, roll = RIG[face]
            transform = carla.Transform(carla.Location(x=x, z=height),
                                        carla.Rotation(pitch=pitch, yaw=yaw, roll=roll))
            sensor = world.spawn_actor(bp, transform, attach_to=vehicle,
                                       attachment_type=carla.AttachmentType.Rigid)
            q: queue.Queue = queue.Queue()
            sensor.listen(q.put)
            rig[(face, modality)] = (sensor, q)
    return rig


def _frame_images(rig: dict, frame: int, timeout: float) -> dict:
    """The image of each sensor for ``frame`` (older images are dropped)."""
    images = {}
    for key, (_, q) in rig.items():
        while True:
            image = q.get(timeout=timeout)
            if image.frame >= frame:
                break
        if image.frame != frame:
            raise RuntimeError(f"sensor {key}: got frame {image.frame}, expected {frame}")
        images[key] = image
    return images


def _vehicle_state(vehicle, snapshot) -> dict:
    t = vehicle.get_transform()
    v = vehicle.get_velocity()
    w = vehicle.get_angular_velocity()
    a = vehicle.get_acceleration()
    return {
        "frame": snapshot.frame,
        "elapsed_seconds": snapshot.timestamp.elapsed_seconds,
        "frame_convention": "CARLA/Unreal: x forward, y right, z up, metres; degrees",
        "location": [t.location.x, t.location.y, t.location.z],
        "rotation_pitch_yaw_roll_deg": [t.rotation.pitch, t.rotation.yaw, t.rotation.roll],
        "velocity": [v.x, v.y, v.z],
        "angular_velocity_deg_s": [w.x, w.y, w.z],
        "acceleration": [a.x, a.y, a.z],
        "rig_rotations_pitch_yaw_roll_deg": RIG,
    }


def main(argv=None) -> int:
    args = parse_args(argv)
    if carla is None:
        print("carla_capture: the CARLA Python API is not installed (pip install carla==<your "
              "server's version>, or add its egg to PYTHONPATH)", file=sys.stderr)
        return 1
    random.seed(args.seed)
    client = carla.Client(args.host, args.port)
    client.set_timeout(args.timeout)
    world = client.load_world(args.town) if args.town else client.get_world()
    original = world.get_settings()
    settings = world.get_settings()
    settings.synchronous_mode = True
    settings.fixed_delta_seconds = args.delta
    world.apply_settings(settings)
    tm = client.get_trafficmanager(args.tm_port)
    tm.set_synchronous_mode(True)
    tm.set_random_device_seed(args.seed)

    actors = []
    try:
        bps = world.get_blueprint_library().filter(args.vehicle)
        bps = [bp for bp in bps if not bp.has_attribute("number_of_wheels")
               or int(bp.get_attribute("number_of_wheels")) == 4] or list(bps)
        spawn_points = world.get_map().get_spawn_points()
        random.shuffle(spawn_points)
        vehicle = None
        for sp in spawn_points:
            vehicle = world.try_spawn_actor(random.choice(bps), sp)
            if vehicle is not None:
                break
        if vehicle is None:
            raise RuntimeError("no free spawn point for the vehicle")
        actors.append(vehicle)
        vehicle.set_autopilot(True, args.tm_port)
        rig = spawn_rig(world, vehicle, args.face_size, args.height, args.x)
        actors.extend(sensor for sensor, _ in rig.values())

        raw = carla.ColorConverter.Raw
        written = 0
        tick = 0
        args.out.mkdir(parents=True, exist_ok=True)
        while written < args.frames:
            frame = world.tick()
            tick += 1
            images = _frame_images(rig, frame, args.timeout)   # drain every tick
            if tick <= args.warmup or (tick - args.warmup) % args.every:
                continue
            folder = args.out / f"{frame:08d}"
            folder.mkdir(parents=True, exist_ok=True)
            for (face, modality), image in images.items():
                _save(image, folder / f"{face}_{modality}.png", raw)
            _atomic_json(folder / "vehicle.json", _vehicle_state(vehicle, world.get_snapshot()))
            written += 1
            print(f"capture {written}/{args.frames}: {folder}", flush=True)
    finally:
        for actor in actors:
            if hasattr(actor, "stop") and actor.is_alive:
                try:
                    actor.stop()
                except RuntimeError:
                    pass
        client.apply_batch([carla.command.DestroyActor(a) for a in actors])
        tm.set_synchronous_mode(False)
        world.apply_settings(original)
    return 0


if __name__ == "__main__":
    sys.exit(main())
