"""The mapper node's services: /splat/map/save (SaveMap), /splat/map/reset (Trigger),
/splat/map/render (RenderPose). Every request is validated first (nodes/service_guard.py):
saves stay inside ``node.output_dir``, reset needs ``node.allow_reset``, renders are bounded
by ``node.max_render_pixels``; a refused or failed request answers success=false + a message.
"""
from __future__ import annotations

from . import service_guard as G
from .node_common import SERVICES


class MapServices:
    def __init__(self, owner):
        from splat_slam_msgs.srv import RenderPose, SaveMap
        from std_srvs.srv import Trigger
        self.owner = owner
        n = owner.node
        n.create_service(SaveMap, SERVICES["save_map"], self.save)
        n.create_service(Trigger, SERVICES["reset_map"], self.reset)
        n.create_service(RenderPose, SERVICES["render"], self.render)

    def save(self, req, resp):
        o = self.owner
        try:
            d = G.save_dir(req.directory, o.output_dir)        # inside node.output_dir only
            with o.worker.lock:
                if o.role.mapper is None:
                    resp.success, resp.message = False, "the map is empty: nothing to save"
                    return resp
                o.role.save(d)
            resp.success = True
            resp.message = f"wrote {d / 'map.ply'}, {d / 'trajectory_keyframes.txt'}, " \
                           f"{d / 'metrics.json'}, {d / 'renders'}" \
                           + (f", {d / 'map_mesh.ply'}" if o.cfg.mapping.mesh else "")
        except Exception as e:
            resp.success, resp.message = False, G.message(e)
        return resp

    def reset(self, req, resp):
        o = self.owner
        try:
            G.check_reset(bool(o.opts["allow_reset"]))            # off unless enabled
            with o.worker.lock:
                o.role.reset()
                o._status()
        except Exception as e:
            resp.success, resp.message = False, G.message(e)
            return resp
        resp.success, resp.message = True, "map reset: the next keyframes start a new map"
        return resp

    def render(self, req, resp):
        from .convert import msg_to_pose
        o = self.owner
        try:
            G.check_pose_msg(req.pose)                                # input first
            with o.worker.lock:
                if o.role.mapper is None:
                    resp.success, resp.message = False, "the map is empty"
                    return resp
                mp = o.role.mapper
                w, h = G.render_size(req.width or o.opts["render_width"], req.height or
                                     o.opts["render_height"], mp.W, mp.H,
                                     o.opts["max_render_pixels"])
                rgb, depth = o._render(msg_to_pose(req.pose), w, h,
                                          G.check_intrinsics(req.intrinsics))
            resp.rgb, resp.depth = o._images(rgb, depth, o.now(), o.frame_id)
            resp.success, resp.message = True, f"rendered {rgb.shape[1]}x{rgb.shape[0]}"
        except Exception as e:
            resp.success, resp.message = False, G.message(e)
        return resp
