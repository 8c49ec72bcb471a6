from gbuffer_export.exr import read_exr_channels
import numpy as np, sys
def load(n):
    ch=read_exr_channels('/tmp/%s.exr'%n); L=[c for c in ch if c.endswith('Combined.R')][0][:-len('Combined.R')]
    return np.stack([ch[L+'Combined.'+c] for c in 'RGB'],-1), ch[L+'Depth.Z']
for tag in sys.argv[1:]:
    a,da=load(tag+'_0'); b,db=load(tag+'_1')
    noise=np.abs(a-b).mean()/np.sqrt(2); mean=(a+b).mean()/2
    print(tag, 'mean %.4f noise %.4f rel %.3f'%(mean,noise,noise/mean), 'depth inf %.3f'%(da>1e9).mean(), 'top rows %.3f'%a[:4].mean(), 'depth med %.2f'%np.median(da[da<1e9]))
