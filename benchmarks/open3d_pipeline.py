"""Open3D's pairwise pipeline as the benchmarks run it (imported inside the fresh processes that
time Open3D; Open3D is a benchmark column, never a dependency): FPFH at ``voxel`` (normals within 2
voxels, features within 5 voxels, at most 100 neighbours), RANSAC (inliers within 1.5 voxels,
Open3D's tutorial checkers, 100,000 iterations / 0.999 confidence) or FGR, then ICP on clouds
downsampled at ``icp_voxel`` with reach 3 ICP voxels."""
import numpy as np
import open3d as o3d

reg = o3d.pipelines.registration


def cloud(points: np.ndarray):
    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))


def features(pcd, voxel: float):
    """The cloud at ``voxel`` with normals, and its FPFH."""
    down = pcd.voxel_down_sample(voxel)
    down.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
    return down, reg.compute_fpfh_feature(down, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel, max_nn=100))


def global_estimate(src_features, tgt_features, voxel: float, method: str = "ransac"):
    """Open3D's RANSAC (or FGR) result between two :func:`features` outputs."""
    (src_down, src_fpfh), (tgt_down, tgt_fpfh) = src_features, tgt_features
    if method == "fgr":
        return reg.registration_fgr_based_on_feature_matching(
            src_down, tgt_down, src_fpfh, tgt_fpfh, reg.FastGlobalRegistrationOption(maximum_correspondence_distance=1.5 * voxel))
    return reg.registration_ransac_based_on_feature_matching(
        src_down, tgt_down, src_fpfh, tgt_fpfh, True, 1.5 * voxel, reg.TransformationEstimationPointToPoint(False), 3,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(1.5 * voxel)],
        reg.RANSACConvergenceCriteria(100000, 0.999))


def icp_clouds(src, tgt, icp_voxel: float, estimator: str):
    """Both clouds at ``icp_voxel``, with normals unless the step is point-to-point."""
    src_icp, tgt_icp = src.voxel_down_sample(icp_voxel), tgt.voxel_down_sample(icp_voxel)
    if estimator != "point_to_point":
        for pcd in (src_icp, tgt_icp):
            pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(20))
    return src_icp, tgt_icp


def refine(src_icp, tgt_icp, icp_voxel: float, initial: np.ndarray, estimator: str):
    """Open3D's ICP (point-to-point, point-to-plane or GICP) from ``initial``, reach 3 ICP voxels."""
    criteria = reg.ICPConvergenceCriteria(relative_fitness=1e-6, relative_rmse=1e-6, max_iteration=50)
    if estimator == "gicp":
        return reg.registration_generalized_icp(src_icp, tgt_icp, 3 * icp_voxel, initial,
                                                reg.TransformationEstimationForGeneralizedICP(), criteria)
    method = reg.TransformationEstimationPointToPoint() if estimator == "point_to_point" \
        else reg.TransformationEstimationPointToPlane()
    return reg.registration_icp(src_icp, tgt_icp, 3 * icp_voxel, initial, method, criteria)
